"""``invert``: stable inversion of 003 (35)-(36) by collocation and IPOPT (or Newton).

One call builds (or reuses) the transcription, computes both equilibria and a
quasi-static initial guess along ``y_ref``, solves, checks the residuals and
returns an :class:`Inverse`.  With ``tol`` it refines the mesh until the
forward-check output error is below ``tol`` (see :func:`invert`).
"""
from __future__ import annotations

import math
import sys
import time
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from ..errors import (BoundaryConditionError, InversionFailed, NoDichotomyError, ReferenceSignalError, RunInterrupted,
                      WallTimeLimitError, INTERRUPT_LIKE, is_interrupt, watch_sigint)
from .boundary import EquilibriumSolver, dichotomy, explain_dichotomy, explain_no_dichotomy, resolve_selection
from .collocation import Transcription, get_scheme
from .result import Inverse
from .servo import ServoModel, check_decoupling

_SERVO_CACHE: dict = {}
_TRANS_CACHE: dict = {}
_EQ_CACHE: dict = {}
_QS_LAST: dict = {}

IPOPT_DEFAULTS = {
    "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
    "ipopt.tol": 1e-10, "ipopt.constr_viol_tol": 1e-10, "ipopt.acceptable_tol": 1e-8,
    "ipopt.linear_solver": "mumps",
    # MUMPS: start with a generous workspace so IPOPT never enters its
    # "increase mem_percent and refactorize" loop on large meshes
    "ipopt.mumps_mem_percent": 4000,
}

#: Extra defaults for square systems (measured in benchmarks/bench_inversion.py, docs/inversion.md):
#: MUMPS's scaling and MC64 permutation in the analysis phase cost ~6 ms of every IPOPT call on a
#: 1.4k-unknown mesh and buy nothing on the banded collocation KKT matrix; AMD ordering; no
#: least-squares multiplier estimate at the start (an extra factorization) and no NLP scaling.
IPOPT_SQUARE_DEFAULTS = {
    "ipopt.mumps_scaling": 0, "ipopt.mumps_permuting_scaling": 0, "ipopt.mumps_pivot_order": 0,
    "ipopt.constr_mult_init_max": 0.0, "ipopt.nlp_scaling_method": "none",
    "ipopt.mu_strategy": "monotone", "ipopt.mu_init": 1e-10,
}


_CACHE_SIZE = 16


def model_key(model) -> str:
    """A structural key of a model: the hash of its serialized symbolic functions, so that
    models built repeatedly by a scene (other parameter values) share servo models,
    transcriptions and equilibrium solvers."""
    key = getattr(model, "_inversion_key", None)
    if key is None:
        import hashlib

        text = "|".join(model.function(k).serialize() for k in ("M", "f", "B", "g", "J", "j", "h"))
        key = hashlib.sha1((model.name + text).encode()).hexdigest()
        try:
            model._inversion_key = key
        except AttributeError:
            pass
    return key


def _remember(cache: dict, key, make):
    if key not in cache:
        if len(cache) >= _CACHE_SIZE:
            cache.pop(next(iter(cache)))
        cache[key] = make()
    return cache[key]


def servo_model(model, formulation: str = "baumgarte", omega: float = 10.0) -> ServoModel:
    """The cached :class:`ServoModel` (keyed by the model's structure, not its parameter values)."""
    return _remember(_SERVO_CACHE, (model_key(model), formulation, float(omega)),
                     lambda: ServoModel(model, formulation, omega))


def transcription(servo, selection, scheme, N: int, objective: float = 0.0, compiled="auto") -> Transcription:
    """The cached :class:`Transcription` for (servo model, selection, scheme, N)."""
    key = (id(servo), selection.start, selection.end, scheme.name, int(N), float(objective), compiled)
    tr = _TRANS_CACHE.get(key)
    if tr is not None and tr.servo is not servo:  # a servo model evicted and its id reused
        del _TRANS_CACHE[key]
    return _remember(_TRANS_CACHE, key,
                     lambda: Transcription(servo, selection, scheme, N, objective=objective, compiled=compiled,
                                           cache_key=_compiled_key(servo, scheme)))


def _compiled_key(servo, scheme) -> str:
    """Disk-cache key of the compiled transcription functions: the model's structure, the index
    reduction, the scheme and the source of the modules that derive the functions from them
    (so that editing them never loads stale code)."""
    global _SOURCE_KEY
    if _SOURCE_KEY is None:
        import hashlib
        from pathlib import Path

        here = Path(__file__).parent
        text = "".join((here / f).read_text() for f in ("servo.py", "collocation.py"))
        _SOURCE_KEY = hashlib.sha1(text.encode()).hexdigest()
    return "|".join([model_key(servo.model), servo.formulation, repr(servo.omega), scheme.name, _SOURCE_KEY])


_SOURCE_KEY: str | None = None


def _equilibrium_solver(model) -> EquilibriumSolver:
    return _remember(_EQ_CACHE, model_key(model), lambda: EquilibriumSolver(model))


#: IPOPT statuses of a solve stopped by its time limit (no continuation after those)
_TIME_LIMIT = ("Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")


class _Progress(ca.Callback):
    """IPOPT iteration callback printing one line per iteration to stderr.

    One per transcription (:func:`_progress_of`), kept alive with it: a cached solver keeps
    calling the callback it was built with, so the callback must not be part of what makes a
    solver new (and must outlive the solve)."""

    def __init__(self, nx, ng, np_, label):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.np_, self.label = nx, ng, np_, label
        self.restart(label)
        self.construct("progress", {})

    def restart(self, label):
        self.label, self.k, self.t = label, 0, time.perf_counter()

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        n = ca.nlpsol_out(i)
        if n in ("f",):
            return ca.Sparsity.dense(1)
        if n in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if n in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        if n == "lam_p":
            return ca.Sparsity.dense(self.np_)
        return ca.Sparsity(0, 0)

    def eval(self, arg):
        g = np.array(arg[ca.nlpsol_out().index("g")]).ravel()
        viol = float(np.max(np.abs(g))) if g.size else 0.0
        print(f"  [{self.label}] iter {self.k:3d}  max|g| = {viol:.3e}  ({time.perf_counter() - self.t:.2f} s)",
              file=sys.stderr, flush=True)
        self.k += 1
        return [0]


def _progress_of(tr, label) -> _Progress:
    cb = getattr(tr, "_progress", None)
    if cb is None:
        cb = tr._progress = _Progress(tr.nX, tr.ng, tr.np, label)
    cb.restart(label)
    return cb


def quasi_static_guess(model, reference, times, q0=None, *, servo=None, where: str = "") -> np.ndarray:
    """Quasi-static inverses along ``y_ref``: equilibria at ``times`` (continued from
    ``q0``), with ``v`` and the multipliers/inputs made consistent with the motion.

    Raises
    ------
    ReferenceSignalError
        Where no equilibrium exists (reference outside the reachable workspace).
    """
    times = np.asarray(times, float)
    if times.size > 1 and np.any(np.diff(times) <= 1e-9 * (times[-1] - times[0])):
        raise ValueError("quasi_static_guess: times must be strictly increasing and distinct (velocities are "
                         "difference quotients)")
    eq = _equilibrium_solver(model)
    n, l, p, m = model.n, model.ell, model.p, model.m
    ys = reference(times)
    th = model.theta_values

    def continuation(idx, w=None):
        out = []
        for k in idx:
            X, _ = eq.solve(ys[:, k], guess_q=q0 if w is None else None, guess_w=w, theta=th,
                            where=f" at t = {times[k]:.4g}{where}")
            w = np.concatenate([X[:n], X[2 * n:]])
            out.append(w)
        return np.array(out).T

    # continuation (one point after the other) on every 4th point keeps the branch of q0; the
    # points between start from the interpolated path and are solved together (batched Newton)
    coarse = np.unique(np.r_[np.arange(0, times.size, 4), times.size - 1])
    Wc = continuation(coarse)
    W0 = np.array([np.interp(times, times[coarse], row) for row in Wc])
    W, res = eq.solve_many(ys, W0, theta=th)
    W[:, coarse] = Wc
    for k in np.flatnonzero(res > 1e-9):  # rare: fall back to continuation from the previous point
        if k not in coarse:
            W[:, k] = continuation([k], W[:, k - 1])[:, 0]
    Q = W[:n]
    V = np.gradient(Q, times, axis=1) if times.size > 2 else np.zeros_like(Q)
    if servo is None:
        return np.vstack([Q, V, W[n:]])
    # multipliers and inputs from the acceleration-level servo constraints at (q, v): A(q, v, z) = 0
    X = np.vstack([Q, V, np.zeros((l + p + m, times.size))])
    Y = servo.reference_samples(reference, times)
    th = model.theta_values
    _pos, _vel, acc = servo.residuals.map(times.size)(X, Y, th)
    Az = np.array(servo.decoupling.map(times.size)(X, Y, th)).reshape(l + p + m, l + p + m, times.size, order="F")
    acc = np.array(acc)
    check_decoupling(model, Az, times, Q)
    Z = np.linalg.solve(Az.transpose(2, 0, 1), -acc.T[:, :, None])[:, :, 0].T
    return np.vstack([Q, V, Z])


def _split(N, lengths, weights):
    """Integers >= 1 (for positive lengths) summing to N, proportional to weights."""
    idx = [i for i, L in enumerate(lengths) if L > 1e-12]
    w = np.array([weights[i] for i in idx], float)
    raw = N * w / w.sum()
    n = np.maximum(1, np.floor(raw).astype(int))
    while n.sum() < N:
        n[np.argmax(raw - n)] += 1
    while n.sum() > N:
        n[np.argmax(n)] -= 1
    out = [0] * len(lengths)
    for i, k in zip(idx, n):
        out[i] = int(k)
    return out


def default_mesh(T0, Tf, t0, tf, N, fraction=0.5):
    """Piecewise-uniform mesh of ``[T0, Tf]`` with ``t0``, ``tf`` as mesh points and
    ``fraction`` of the ``N`` intervals on ``[t0, tf]`` (the rest by length)."""
    knots = [T0, max(T0, t0), min(Tf, tf), Tf]
    lengths = np.diff(knots)
    side = lengths[0] + lengths[2]
    weights = [(1 - fraction) * lengths[0] / side if side > 0 else 0, fraction,
               (1 - fraction) * lengths[2] / side if side > 0 else 0]
    counts = _split(N, lengths, weights)
    parts = [np.linspace(a, b, k + 1)[:-1] for a, b, k in zip(knots[:-1], knots[1:], counts) if k > 0]
    return np.concatenate(parts + [[Tf]])


def _newton(tr, x0, p, *, max_iter, max_wall_time, tol, progress, label, banded=True):
    """Newton's method on the square collocation system with Jacobian reuse.

    Residual and Jacobian come from :meth:`Transcription.evaluators`; the Jacobian, permuted
    to time order, is a band matrix factorized by LAPACK's banded LU (SuperLU when the band
    is too wide or ``banded=False``). The factorization is kept (also across calls on the
    same transcription, e.g. re-solves after a parameter change) while it contracts the
    residual by at least a factor 4 per step (simplified Newton), and refreshed
    otherwise; a refreshed step that does not decrease the residual is damped."""
    x = np.array(x0, float)
    t_start = time.perf_counter()
    residual, residual_and_jacobian = tr.evaluators()
    band = tr.banded_pattern() if banded else None
    band = band if band is not None and band.worthwhile else None
    g = residual(x, p)
    nrm = np.linalg.norm(g)
    lu = getattr(tr, "_lu", None)
    fresh = False
    status, it, n_fact = "Maximum_Iterations_Exceeded", 0, 0
    for it in range(1, max_iter + 1):
        if np.max(np.abs(g)) < tol:
            status = "Solve_Succeeded"
            it -= 1
            break
        if time.perf_counter() - t_start > max_wall_time:
            status = "Maximum_WallTime_Exceeded"
            break
        if lu is not None and not fresh:
            dx = -lu.solve(g)
            g2 = residual(x + dx, p)
            n2 = np.linalg.norm(g2)
            if np.isfinite(n2) and (n2 <= 0.25 * nrm or np.max(np.abs(g2)) < tol):
                x, g, nrm = x + dx, g2, n2
                if progress:
                    print(f"  [{label}] newton {it:3d}  max|g| = {np.max(np.abs(g)):.3e}  (reused Jacobian)",
                          file=sys.stderr)
                continue
        _, J = residual_and_jacobian(x, p)
        try:
            lu = band.factor(J.data) if band is not None else spl.splu(J, permc_spec="COLAMD")
            n_fact += 1
        except RuntimeError:
            status = "Singular_Jacobian"
            break
        fresh = True
        dx = -lu.solve(g)
        s = 1.0
        while True:
            g2 = residual(x + s * dx, p)
            n2 = np.linalg.norm(g2)
            if np.isfinite(n2) and (n2 <= (1 - 1e-4 * s) * nrm or np.max(np.abs(g2)) < tol):
                break
            s *= 0.5
            if s < 1e-6:
                break
        if s < 1e-6:
            status = "Line_Search_Failed"
            break
        x, g, nrm = x + s * dx, g2, n2
        fresh = s < 1.0  # after a damped step refresh again
        if progress:
            print(f"  [{label}] newton {it:3d}  max|g| = {np.max(np.abs(g)):.3e}  step {s:.3g}", file=sys.stderr)
    else:
        if np.max(np.abs(g)) < tol:
            status = "Solve_Succeeded"
    if lu is not None and status == "Solve_Succeeded":
        tr._lu = lu
    return x, {"status": status, "iterations": it, "success": status == "Solve_Succeeded",
               "max_constraint_violation": float(np.max(np.abs(g))), "factorizations": n_fact}


def invert(model, reference, *, T0: float | None = None, Tf: float | None = None, start: dict | None = None,
           end: dict | None = None, N: int = 200,
           mesh: np.ndarray | None = None, scheme: str = "hermite-simpson", formulation: str = "baumgarte",
           omega: float = 10.0, backend: str = "ipopt", ipopt_options: dict | None = None,
           max_iter: int = 100, max_wall_time: float = 120.0, newton_tol: float = 1e-10,
           warm_start: Inverse | None = None, q_guess=None, objective: float | None = None,
           allow_underdetermined: bool = False, residual_tol: float = 1e-4, tol: float | None = None,
           max_refinements: int = 6, max_N: int = 4000, forward_options: dict | None = None,
           progress: bool = False, continuation: bool = True, mesh_fraction: float | None = None,
           compiled: bool | str = "auto", plan=None, plan_options: dict | None = None) -> Inverse:
    """Stable inversion by servo constraints (003 (35)) with boundary conditions (36).

    Parameters
    ----------
    model : Model
        The reference model (003 (1)); ``h`` must depend on ``q`` only.
    reference : Reference
        ``y_ref``; needs three continuous derivatives (jerk-level index reduction).
    T0, Tf : float, optional
        The BVP horizon, ``T0 <= t0`` and ``Tf >= tf`` (pre- and post-actuation).
    start, end : dict, optional
        Boundary selection by name (:mod:`invctl.inversion.boundary`).  Whatever of
        ``T0, Tf, start, end`` is ``None`` is derived by
        :func:`invctl.inversion.plan.plan_inversion` (from the modes of the linearized
        inverse model at the equilibria, with ``plan_options``); given ones are kept.
        The plan goes to ``diagnostics["plan"]``.
    plan : InversionPlan, optional
        A plan computed before (fills what is ``None``; e.g. reused across a sweep).
    plan_options : dict, optional
        Keywords of ``plan_inversion`` (``tol``, ``max_horizon``, ``neutral``, ``scale``).
    N, mesh : int or array
        Number of intervals, or the mesh itself.  The default mesh has ``t0`` and ``tf``
        as mesh points (the fourth derivative of a C^4 reference jumps there; inside an
        interval it costs an order of magnitude in accuracy).  With a given horizon it is
        piecewise uniform with ``mesh_fraction`` (default 0.5) of the intervals on
        ``[t0, tf]``; when ``T0`` or ``Tf`` is derived (and ``mesh_fraction=None``) it is
        uniform on ``[t0, tf]`` and graded outside by the decay of the tails
        (:func:`invctl.inversion.plan.graded_mesh`).
    scheme : str
        ``hermite-simpson`` (default), ``legendre<d>``, ``radau<d>``.
    formulation, omega : str, float
        Index reduction (:mod:`invctl.inversion.servo`); default Baumgarte-stabilized
        jerk level with rate 10/s.
    backend : {"ipopt", "newton"}
        IPOPT (default; options pass through ``ipopt_options`` verbatim, e.g.
        ``{"ipopt.tol": 1e-12}``) or a sparse Newton method with line search on the
        square system (SuperLU).
    max_iter, max_wall_time : int, float
        Limits of every solve.
    warm_start : Inverse, optional
        An earlier solution (any mesh) used as initial guess.
    q_guess : array, optional
        Configuration to start the equilibrium search at ``T0``.
    objective : float, optional
        Weight of the input energy; used when the inverse is not unique
        (``allow_underdetermined`` with fewer than ``2n+l+p+m`` conditions).
    residual_tol : float
        Largest accepted position-level constraint residual at the mesh.
    tol : float, optional
        Requested forward-check output error: refine the mesh (error-driven,
        warm-started) until met; meshes tried go to ``diagnostics["meshes"]``.
    progress : bool
        One line per iteration to stderr.
    compiled : bool or "auto"
        Evaluate the per-node/per-interval functions as C code compiled once and
        cached on disk (:mod:`invctl.inversion.compiled`); square systems only.
        ``"auto"`` (default) uses the compiled code only when it is already in the
        cache (compiling costs ~10 s once, which a single solve never recovers);
        ``True`` compiles when missing, ``False`` never.
    continuation : bool
        When a cold solve fails, solve a slower transition first and continue.

    Raises
    ------
    BoundaryConditionError, ReferenceSignalError, InversionFailed
        ``InversionFailed.partial`` is the last iterate as an :class:`Inverse`;
        subclasses name the cause: ``NoDichotomyError`` (internal eigenvalues on the
        imaginary axis), ``HorizonTooLongError``, ``ReferenceSmoothnessError``,
        ``SingularDecouplingError`` (a ``RelativeDegreeError``), ``PositionOutputError``
        (a ``ModelError``).
    """
    if plan is not None and plan_options is not None:
        raise ValueError("invert: give either plan (computed before) or plan_options (to compute one), not both")
    if plan is None and (plan_options is not None or None in (T0, Tf, start, end)):
        from .plan import plan_inversion

        plan = plan_inversion(model, reference, start=start, end=end, T0=T0, Tf=Tf, formulation=formulation,
                              omega=omega, q_guess=q_guess, **(plan_options or {}))
    if plan is not None:
        if (plan.formulation, plan.omega) != (formulation, float(omega)):
            raise ValueError(f"invert: the plan was made for formulation={plan.formulation!r}, omega={plan.omega}, "
                             f"not {formulation!r}, {omega}")
        T0 = plan.T0 if T0 is None else T0
        Tf = plan.Tf if Tf is None else Tf
        start = plan.start if start is None else start
        end = plan.end if end is None else end
    if tol is not None:
        return _refine(model, reference, T0=T0, Tf=Tf, start=start, end=end, N=N, mesh=mesh, scheme=scheme,
                       formulation=formulation, omega=omega, backend=backend, ipopt_options=ipopt_options,
                       max_iter=max_iter, max_wall_time=max_wall_time, newton_tol=newton_tol,
                       warm_start=warm_start, q_guess=q_guess, objective=objective,
                       allow_underdetermined=allow_underdetermined, residual_tol=residual_tol, tol=tol,
                       max_refinements=max_refinements, max_N=max_N, forward_options=forward_options,
                       progress=progress, continuation=continuation, mesh_fraction=mesh_fraction,
                       compiled=compiled, plan=plan)
    from .plan import check_reference

    check_reference(reference, 3)
    if not (T0 <= reference.t0 and Tf >= reference.tf and Tf > T0):
        raise ReferenceSignalError(f"the horizon [T0, Tf] = [{T0}, {Tf}] must contain [t0, tf] = "
                                   f"[{reference.t0}, {reference.tf}] (pre- and post-actuation)")
    t_build = time.perf_counter()
    sch = get_scheme(scheme)
    servo = servo_model(model, formulation, omega)
    sel = resolve_selection(servo, start, end, allow_underdetermined=allow_underdetermined)
    if mesh is not None:
        t_mesh = np.asarray(mesh, float)
        N = t_mesh.size - 1
        if N < 2 or np.any(np.diff(t_mesh) <= 0) or abs(t_mesh[0] - T0) > 1e-12 or abs(t_mesh[-1] - Tf) > 1e-12:
            raise ValueError("mesh must be increasing from T0 to Tf with at least 3 points")
    elif plan is not None and mesh_fraction is None and {"T0", "Tf"} & set(plan.derived):
        from .plan import graded_mesh

        t_mesh = graded_mesh(T0, Tf, reference.t0, reference.tf, int(N), plan.mesh_decay(sch.order))
    else:
        t_mesh = default_mesh(T0, Tf, reference.t0, reference.tf, int(N), 0.5 if mesh_fraction is None
                              else mesh_fraction)
    under = len(sel.start) + len(sel.end) < servo.layout.nx
    weight = float(objective) if objective is not None else (1.0 if under else 0.0)
    tr = transcription(servo, sel, sch, N, weight, compiled=compiled if not under else False)
    build_s = time.perf_counter() - t_build
    # equilibria and initial guess
    t_guess = time.perf_counter()
    q0 = q_guess if q_guess is not None else np.zeros(model.n)
    qs_times = np.unique(np.concatenate([np.linspace(T0, Tf, 21), np.linspace(reference.t0, reference.tf, 41)]))
    qs_times = qs_times[np.r_[True, np.diff(qs_times) > 1e-9 * (Tf - T0)]]  # 0.95 from both grids
    last = _QS_LAST.get("entry")
    if (last is not None and last[0] is model and last[1] is reference and last[2] == (T0, Tf)
            and np.array_equal(last[3], q0)):
        G = last[4]  # mesh refinement: same model, reference and horizon
    else:
        G = quasi_static_guess(model, reference, qs_times, q0, servo=servo)
        _QS_LAST["entry"] = (model, reference, (T0, Tf), np.array(q0, float), G)
    E0 = np.concatenate([G[:model.n, 0], np.zeros(model.n), G[2 * model.n:, 0]])
    Ef = np.concatenate([G[:model.n, -1], np.zeros(model.n), G[2 * model.n:, -1]])
    # exact equilibria (the ends of the quasi-static path are static already, re-solve to be sure)
    eq = _equilibrium_solver(model)
    E0, _ = eq.solve(reference(T0).ravel(), guess_w=np.concatenate([E0[:model.n], E0[2 * model.n:]]),
                     theta=model.theta_values,
                     where=f" at T0 = {T0}")
    Ef, _ = eq.solve(reference(Tf).ravel(), guess_w=np.concatenate([Ef[:model.n], Ef[2 * model.n:]]),
                     theta=model.theta_values,
                     where=f" at Tf = {Tf}")
    dich = None
    if not under:
        Yends = servo.reference_samples(reference, np.array([T0, Tf]))
        dich = dichotomy(servo, sel, E0, Yends[:, :1], Ef, Yends[:, 1:], model.theta_values)
        if dich["neutral_internal"] and sel.end:  # all at T0: an initial value problem, no dichotomy needed
            raise NoDichotomyError(explain_no_dichotomy(dich["eigenvalues_internal_start"],
                                                        dich["eigenvalues_internal_end"], f" for {model.name!r}"),
                                   diagnostics={k: v for k, v in dich.items() if not k.startswith("eigenvalues")})
        if dich["well_posed"] is False:
            raise BoundaryConditionError(explain_dichotomy(dich, sel), diagnostics={
                k: v for k, v in dich.items() if not k.startswith("eigenvalues")})
    tc = tr.collocation_times(t_mesh)
    if warm_start is not None:
        x0 = tr.pack(warm_start.X(t_mesh), warm_start.X(tc) if tc.size else None)
    else:
        interp = lambda tt: np.vstack([np.interp(tt, qs_times, row) for row in G])  # noqa: E731
        x0 = tr.pack(interp(t_mesh), interp(tc) if tc.size else None)
    Y = servo.reference_samples(reference, tr.sample_times(t_mesh))
    theta = model.theta_values
    p = tr.parameters(t_mesh, Y, theta, E0, Ef)
    guess_s = time.perf_counter() - t_guess
    label = f"{sch.name} N={N}"
    x, info, solve_s, build_solver_s = _solve(tr, x0, p, backend=backend, ipopt_options=ipopt_options,
                                              max_iter=max_iter, max_wall_time=max_wall_time,
                                              newton_tol=newton_tol, progress=progress, label=label,
                                              square=not under)
    build_s += build_solver_s
    cont_info = None
    if not info["success"] and continuation and warm_start is None and info["status"] not in _TIME_LIMIT:
        x, info, cont_info = _continuation(model, reference, tr, servo, t_mesh, x0, E0, Ef, theta,
                                           backend=backend, ipopt_options=ipopt_options, max_iter=max_iter,
                                           max_wall_time=max_wall_time, newton_tol=newton_tol,
                                           progress=progress, label=label, square=not under)
        solve_s += cont_info.pop("solve_s")
    inv = _make_inverse(model, reference, servo, tr, sch, t_mesh, x, theta)
    res = _residuals(inv, servo, reference, theta)
    inv.diagnostics.update(info)
    inv.diagnostics.update({
        "backend": backend, "scheme": sch.name, "N": int(N), "formulation": formulation, "omega": omega,
        "build_s": build_s, "solve_s": solve_s, "guess_s": guess_s, "unknowns": tr.nX, "equations": tr.ng,
        "selection": sel.describe(), "T0": T0, "Tf": Tf, "residuals": res, "continuation": cont_info,
        "compiled": tr.compiled,
        "dichotomy": None if dich is None else {k: v for k, v in dich.items() if not k.startswith("eigenvalues")},
        "plan": None if plan is None else plan.to_dict(),
        "mesh": "given" if mesh is not None else ("graded" if plan is not None and mesh_fraction is None
                                                  and {"T0", "Tf"} & set(plan.derived) else "piecewise uniform"),
    })
    if not info["success"] and info["status"] in _TIME_LIMIT:
        raise WallTimeLimitError(
            f"stable inversion stopped at the wall-time limit of {max_wall_time:g} s after {info['iterations']} "
            f"iterations ({backend}, {label}, max constraint violation "
            f"{info.get('max_constraint_violation', float('nan')):.3g}); raise max_wall_time (invert(..., "
            "max_wall_time=...) or the scene's Tracking(inversion={'max_wall_time': ...})) or use fewer intervals "
            "(N); the last iterate is in exc.partial", partial=inv, diagnostics=inv.diagnostics)
    if not info["success"]:
        raise InversionFailed(
            f"stable inversion failed ({backend}: {info['status']} after {info['iterations']} iterations, "
            f"max constraint violation {info.get('max_constraint_violation', float('nan')):.3g}) on {label}. "
            "Try a finer mesh (N), a longer horizon, warm_start from a coarser solution, more iterations "
            "(max_iter) or another boundary selection; the last iterate is in exc.partial",
            partial=inv, diagnostics=inv.diagnostics)
    if res["position_mesh"] > residual_tol:
        raise InversionFailed(
            f"the solution violates the position-level constraints g = 0, h = y_ref by "
            f"{res['position_mesh']:.3g} > residual_tol = {residual_tol:.3g} at the mesh ({label}); refine the "
            "mesh or check the boundary selection (drift modes must be fixed)", partial=inv,
            diagnostics=inv.diagnostics)
    return inv


def _solve(tr, x0, p, *, backend, ipopt_options, max_iter, max_wall_time, newton_tol, progress, label, square,
           lam_g0=None, assembled_jacobian=True):
    t0 = time.perf_counter()
    if backend == "newton":
        if not square:
            raise ValueError("backend='newton' needs a square system (2n+l+p+m boundary conditions)")
        tr.evaluators()
        build = time.perf_counter() - t0
        t1 = time.perf_counter()
        x, info = _newton(tr, x0, p, max_iter=max_iter, max_wall_time=max_wall_time, tol=newton_tol,
                          progress=progress, label=label)
        return x, info, time.perf_counter() - t1, build
    if backend != "ipopt":
        raise ValueError(f"backend must be 'ipopt' or 'newton', got {backend!r}")
    opts: dict[str, Any] = dict(IPOPT_DEFAULTS)
    opts["ipopt.max_iter"] = int(max_iter)
    opts["ipopt.max_wall_time"] = float(max_wall_time)
    if square:
        # square system: the primal step solves J dx = -g whatever the Hessian (exact zero Hessian,
        # Transcription.ipopt); without bounds the barrier parameter plays no role
        opts.update(IPOPT_SQUARE_DEFAULTS)
    opts.update(ipopt_options or {})
    if progress:
        opts["iteration_callback"] = _progress_of(tr, label)
    zero_hessian = (square and assembled_jacobian
                    and opts.get("ipopt.hessian_approximation", "exact") == "exact")
    solver = tr.ipopt(opts, assembled_jacobian=assembled_jacobian, zero_hessian=zero_hessian)
    build = time.perf_counter() - t0
    t1 = time.perf_counter()
    args = {"x0": x0, "p": p, "lbg": 0, "ubg": 0}
    if lam_g0 is not None:
        args["lam_g0"] = lam_g0
    with watch_sigint() as sigint:  # Ctrl-C inside IPOPT ends as User_Requested_Stop: an interruption
        try:
            sol = solver(**args)
        except RuntimeError as exc:  # a Ctrl-C caught in a Python callback (progress) aborts the call
            if not sigint.seen:
                raise
            raise RunInterrupted(f"interrupted during the IPOPT solve on {label}",
                                 diagnostics={"solver": str(exc).splitlines()[-1][:200]}) from None
    solve_s = time.perf_counter() - t1
    st = solver.stats()
    if sigint.seen and not st.get("success", False):
        raise RunInterrupted(f"interrupted during the IPOPT solve on {label} after {st.get('iter_count', '?')} "
                             "iterations", diagnostics={"status": st.get("return_status", "?"),
                                                        "iterations": int(st.get("iter_count", -1))})
    g = np.array(sol["g"]).ravel()
    viol = float(np.max(np.abs(g))) if g.size else 0.0
    ok = bool(st.get("success", False)) or (st.get("return_status") == "Solved_To_Acceptable_Level" and viol < 1e-8)
    info = {"status": st.get("return_status", "?"), "iterations": int(st.get("iter_count", -1)),
            "success": ok, "max_constraint_violation": viol}
    return np.array(sol["x"]).ravel(), info, solve_s, build


def _continuation(model, reference, tr, servo, t_mesh, x0, E0, Ef, theta, **kw):
    """Homotopy from the quasi-static problem: reference samples scaled in time
    (slower transition, s -> 1), each step warm-started from the last."""
    from ..reference import Reference

    steps = []
    x = x0
    total = 0.0
    info = {"success": False, "status": "not run", "iterations": 0}
    for stretch in (4.0, 2.0, 1.4, 1.0):
        t = reference.t
        tc = reference.t0
        slow = ca.substitute(reference.expr, t, tc + (t - tc) / stretch)
        ref_s = Reference(t, slow, reference.t0, reference.t0 + stretch * (reference.tf - reference.t0),
                          reference.smoothness, reference.name)
        Y = servo.reference_samples(ref_s, tr.sample_times(t_mesh))
        p = tr.parameters(t_mesh, Y, theta, E0, Ef)
        x, info, s, _ = _solve(tr, x, p, **kw)
        total += s
        steps.append({"stretch": stretch, "status": info["status"], "iterations": info["iterations"]})
        if not info["success"]:
            break
    return x, info, {"steps": steps, "solve_s": total}


def _make_inverse(model, reference, servo, tr, sch, t_mesh, x, theta) -> Inverse:
    Xmesh, Xcol = tr.unpack(x)
    dX = np.zeros_like(Xmesh)
    if sch.is_hs:
        Yn = servo.reference_samples(reference, t_mesh)
        dX = np.array(servo.rhs.map(t_mesh.size)(Xmesh, Yn, theta))
    L = servo.layout
    return Inverse(sch.name, t_mesh, Xmesh, dX, Xcol, {"n": L.n, "l": L.l, "p": L.p, "m": L.m},
                   reference.t0, reference.tf, servo.names, {}, y_ref_fn=reference)


def _residuals(inv: Inverse, servo, reference, theta, samples_per_interval: int = 4) -> dict:
    """Constraint residuals of (35) at the mesh and between mesh points: ``position``
    (``g`` and ``h - y_ref`` together), ``holonomic`` (``g``), ``servo`` (``h - y_ref``),
    ``velocity`` and ``acceleration`` levels."""
    tm = inv.t_mesh
    s = np.linspace(0, 1, samples_per_interval + 1)[1:-1]
    tt = (tm[:-1, None] + np.diff(tm)[:, None] * s[None, :]).ravel()
    out = {}
    for name, t in (("mesh", tm), ("between", tt)):
        X = inv.X(t)
        Y = servo.reference_samples(reference, t)
        pos, vel, acc = (np.array(r) for r in servo.residuals.map(t.size)(X, Y, theta))
        out[f"position_{name}"] = float(np.max(np.abs(pos))) if pos.size else 0.0
        nl = servo.layout.l
        out[f"holonomic_{name}"] = float(np.max(np.abs(pos[:nl]))) if nl else 0.0
        out[f"servo_{name}"] = float(np.max(np.abs(pos[nl:]))) if pos[nl:].size else 0.0
        out[f"velocity_{name}"] = float(np.max(np.abs(vel))) if vel.size else 0.0
        out[f"acceleration_{name}"] = float(np.max(np.abs(acc))) if acc.size else 0.0
    out["position"] = max(out["position_mesh"], out["position_between"])
    return out


def interval_errors(inv: Inverse, servo, reference, theta) -> np.ndarray:
    """Local error estimate per interval: ``h_k * max |X'(t) - F(X(t), t)|`` of the
    collocation polynomial at points that are not collocation points (scaled per
    component by ``1 + max |X|``)."""
    tm = inv.t_mesh
    h = np.diff(tm)
    s = np.array([0.17, 0.33, 0.67, 0.83])
    tt = (tm[:-1, None] + h[:, None] * s[None, :]).ravel()
    eps = 1e-6 * h.min()
    dXn = (inv.X(tt + eps) - inv.X(tt - eps)) / (2 * eps)
    Y = servo.reference_samples(reference, tt)
    F = np.array(servo.rhs.map(tt.size)(inv.X(tt), Y, theta))
    scale = 1.0 + np.max(np.abs(inv.X_mesh), axis=1, keepdims=True)
    err = np.max(np.abs(dXn - F) / scale, axis=0).reshape(h.size, s.size).max(axis=1)
    return err * h


def _refine(model, reference, *, tol, **kw):
    """:func:`_refine_meshes`; on Ctrl-C, :class:`RunInterrupted` with the last accepted mesh's inverse
    (solved and forward-checked, ``tol`` not met yet) in ``partial``."""
    state = {"meshes": [], "accepted": None}
    try:
        return _refine_meshes(model, reference, state, tol=tol, **kw)
    except INTERRUPT_LIKE as exc:
        if not is_interrupt(exc):
            raise
        last, meshes = state["accepted"], state["meshes"]
        note = f"mesh refinement interrupted after {len(meshes)} complete mesh(es)"
        if last is not None:
            last.diagnostics.update({"meshes": meshes, "max_output_error": meshes[-1]["error"], "tol": tol,
                                     "partial": note})
        raise RunInterrupted(
            note + ("; the last accepted mesh (N = {}, forward-check error {:.3g}, tol {:.2g} not met) is in "
                    "exc.partial".format(last.N, meshes[-1]["error"], tol) if last is not None
                    else "; no mesh was complete") + (f" ({exc})" if str(exc) else ""),
            partial=last, diagnostics={"meshes": meshes}) from None


def _refine_meshes(model, reference, state, *, tol, max_refinements, max_N, forward_options, N, mesh, warm_start,
                   **kw):
    from .verify import forward_check

    sch = get_scheme(kw["scheme"])
    meshes = state["meshes"]
    inv = warm_start
    total_build = total_solve = 0.0
    t_mesh = None if mesh is None else np.asarray(mesh, float)
    for it in range(max_refinements + 1):
        inv = invert(model, reference, N=N, mesh=t_mesh, warm_start=inv, **kw)
        fc = forward_check(model, inv, reference, **(forward_options or {}))
        total_build += inv.diagnostics["build_s"]
        total_solve += inv.diagnostics["solve_s"]
        meshes.append({"N": inv.N, "error": fc["error"], "iterations": inv.diagnostics["iterations"],
                       "solve_s": inv.diagnostics["solve_s"], "build_s": inv.diagnostics["build_s"]})
        state["accepted"] = inv
        if kw.get("progress"):
            print(f"  refinement {it}: N = {inv.N}, forward-check error {fc['error']:.3e} (tol {tol:.1e})",
                  file=sys.stderr)
        if fc["error"] <= tol:
            inv.diagnostics.update({"meshes": meshes, "max_output_error": fc["error"], "forward_check": {
                k: fc[k] for k in ("error", "t_worst", "window", "windows", "rate")}, "tol": tol,
                "total_build_s": total_build, "total_solve_s": total_solve})
            return inv
        if it == max_refinements or inv.N >= max_N:
            break
        servo = servo_model(model, kw["formulation"], kw["omega"])
        err = np.maximum(interval_errors(inv, servo, reference, model.theta_values), 1e-300)
        h = np.diff(inv.t_mesh)
        order = sch.order
        factor = min(4.0, max(1.5, (fc["error"] / tol) ** (1.0 / order) * 1.2))
        N = min(max_N, int(math.ceil(inv.N * factor)))
        dens = (err / h ** (order + 1)) ** (1.0 / (order + 1))
        dens = np.maximum(dens, 0.05 * dens.max())
        cum = np.concatenate([[0.0], np.cumsum(dens * h)])
        knots = [inv.T0, reference.t0, reference.tf, inv.Tf]
        ck = np.interp(knots, inv.t_mesh, cum)
        counts = _split(N, np.diff(knots), np.diff(ck))
        parts = [np.interp(np.linspace(ck[i], ck[i + 1], counts[i] + 1)[:-1], cum, inv.t_mesh)
                 for i in range(3) if counts[i] > 0]
        t_mesh = np.concatenate(parts + [[inv.Tf]])
        t_mesh[0], t_mesh[-1] = inv.T0, inv.Tf
    tried = ", ".join(f"N={m['N']}: {m['error']:.2g}" for m in meshes)
    raise InversionFailed(
        f"mesh refinement did not reach the output error {tol:.2g}; meshes tried (forward-check error): {tried}; "
        "raise max_refinements/max_N or use a higher-order scheme (legendre3)", partial=inv,
        diagnostics={"meshes": meshes})
