"""Parameter sensitivities of a stable inverse and warm re-solves at nearby parameters.

The collocation of the inverse model 003 (35) with the boundary conditions 003 (36) is a square
system ``g(x, p) = 0`` in the unknowns ``x`` (states at the mesh and collocation points) and the
parameters ``p = (h, Y, theta, E0, Ef)`` (steps, reference samples, model parameters and the
two equilibria, :class:`~invctl.inversion.collocation.Transcription`).  At a solution with a
nonsingular Jacobian the implicit function theorem gives

    dx/dtheta = -(dg/dx)^-1 (dg/dtheta + dg/dE0 dE0/dtheta + dg/dEf dEf/dtheta),

one factorization of the Jacobian the Newton method already assembles and one
back-substitution per parameter, no re-solve.  The equilibria move with ``theta`` too
(``dE/dtheta`` by the implicit function theorem on the equilibrium equations).  The output
reference ``y_ref(t)`` is held fixed: the sensitivities answer "which feedforward makes a plant
with other parameters follow the same ``y_ref``".

:class:`ParametricInverse` holds a solved inverse with its collocation system; it gives the
sensitivities (:meth:`~ParametricInverse.sensitivities`) and re-solves the same transcription for
other parameters or references by Newton's method from its own solution (continuation,
:meth:`~ParametricInverse.resolve`) -- the building block of trajectory libraries
(:mod:`invctl.studies.library`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.sparse.linalg as spl

from ..errors import BoundaryConditionError, InversionFailed, ParameterError
from .boundary import Selection, dichotomy, explain_dichotomy
from .schemes import get_scheme
from .result import Inverse
from .backends import _newton
from .cache import equilibrium_solver, model_key, servo_model, transcription
from .guess import quasi_static_guess
from .square import make_inverse


def _selection(servo, text: str) -> Selection:
    """The :class:`Selection` whose ``describe()`` is ``text`` (as in ``diagnostics["selection"]``)."""
    labels = tuple(f"{k}:{nm}" for k in ("q", "v", "lam", "mu", "u") for nm in servo.names[k])
    parts = [s.strip() for s in str(text).split(";")]
    if len(parts) != 2 or not parts[0].startswith("at T0:") or not parts[1].startswith("at Tf:"):
        raise BoundaryConditionError(f"cannot read the boundary selection {text!r}; give start= and end=")
    sides = []
    for part in parts:
        body = part.split(":", 1)[1].strip()
        entries = [] if body in ("", "-") else [e.strip() for e in body.split(",")]
        unknown = [e for e in entries if e not in labels]
        if unknown:
            raise BoundaryConditionError(f"boundary selection {text!r} names {unknown}, not entries of this "
                                         f"model's unknowns {list(labels)}")
        sides.append(tuple(labels.index(e) for e in entries))
    return Selection(sides[0], sides[1], labels)


def mapped_mesh(t_mesh, knots_from, knots_to) -> np.ndarray:
    """``t_mesh`` mapped piecewise linearly from ``[T0, t0, tf, Tf]`` to other knots (the same
    number of intervals before, during and after the transition, so a solution vector of one
    problem is a warm start for the other)."""
    a, b = np.asarray(knots_from, float), np.asarray(knots_to, float)
    if np.any(np.diff(b) < 0) or not b[-1] > b[0]:
        raise ValueError(f"mesh knots must be non-decreasing with Tf > T0, got {b.tolist()}")
    out = np.interp(t_mesh, a, b) if np.all(np.diff(a) > 0) else _interp_segments(t_mesh, a, b)
    out[0], out[-1] = b[0], b[-1]
    return out


def _interp_segments(t, a, b):
    out = np.empty_like(t)
    for i in range(3):
        sel = (t >= a[i]) & (t <= a[i + 1])
        if a[i + 1] > a[i]:
            out[sel] = b[i] + (t[sel] - a[i]) * (b[i + 1] - b[i]) / (a[i + 1] - a[i])
        else:
            out[sel] = b[i]
    return out


def parameter_chain(model, names=None, *, derived: bool = True) -> np.ndarray:
    """``d theta / d p``: how the model's parameter column moves with the named parameters.

    ``derived=True`` follows the model's derived parameters that are not overridden (e.g.
    ``I3 = m3 L3^2 / 12`` moves with ``m3``), evaluated symbolically from the rules; a rule that
    CasADi cannot evaluate (Python ``math`` functions) is differentiated by central differences
    (relative step 1e-6, error ~1e-10 relative for smooth rules).  Shape ``(ntheta, len(names))``.
    """
    pnames = list(model.params.names)
    names = pnames if names is None else list(names)
    unknown = [n for n in names if n not in pnames]
    if unknown:
        raise ParameterError(f"model {model.name!r}: unknown parameter(s) {unknown}; known: {pnames}")
    rules = {k: r for k, r in model.derived.items() if k not in model.overrides} if derived else {}
    D = np.zeros((len(pnames), len(names)))
    for j, nm in enumerate(names):
        D[pnames.index(nm), j] = 1.0
    follow = [j for j, nm in enumerate(names) if nm not in rules]  # a derived name itself moves alone
    if not rules or not follow:
        return D
    try:
        sym = {k: ca.SX.sym(k) for k in pnames}
        vals = dict(sym)
        for k, rule in model.derived.items():
            if k in rules:
                vals[k] = ca.SX(rule(vals))
        expr = ca.vertcat(*[vals[k] for k in pnames])
        allsym = ca.vertcat(*sym.values())
        # a rule CasADi only seemed to trace (math.sqrt of a symbol gives a constant nan) does not reproduce the
        # resolved values: then central differences
        traced = np.array(ca.Function("theta_of_p", [allsym], [expr])(model.theta_values)).ravel()
        if not np.allclose(traced, model.theta_values, rtol=1e-12, atol=0.0):
            raise ValueError("a derived-parameter rule is not traced by CasADi")
        jac = ca.Function("dtheta_dp", [allsym], [ca.jacobian(expr, allsym)])
        full = np.array(jac(model.theta_values))
        for j in follow:
            D[:, j] = full[:, pnames.index(names[j])]
        return D
    except Exception:  # a rule with Python math: central differences on the resolution
        from ..model.params import resolve_params

        for j in follow:
            nm = names[j]
            v = model.values[nm]
            h = 1e-6 * max(abs(v), 1e-3)
            plus = resolve_params(model.defaults, model.derived, {**model.overrides, nm: v + h})
            minus = resolve_params(model.defaults, model.derived, {**model.overrides, nm: v - h})
            D[:, j] = [(plus[k] - minus[k]) / (2 * h) for k in pnames]
        return D


def _functions(servo):
    """Per servo model: ``dF/dtheta`` and the equilibrium residual's Jacobians (SX, built once, kept by it)."""
    fns = servo.derived.get("sensitivity")
    if fns is None:
        md, L = servo.model, servo.layout
        X, Y, th = ca.SX.sym("X", L.nx), ca.SX.sym("Y", 4 * L.m), ca.SX.sym("theta", md.theta.shape[0])
        F = servo.rhs(X, Y, th)
        dF = ca.Function("servo_rhs_theta", [X, Y, th], [ca.densify(ca.jacobian(F, th))], ["X", "Y", "theta"],
                         ["dFdtheta"])
        # equilibrium equations (v = 0): g(q), j(q), h(q) - y, f(q, 0) + G^T lam + J^T mu + B u
        n, l, p, m = md.n, md.ell, md.p, md.m
        w, y = ca.SX.sym("w", n + l + p + m), ca.SX.sym("y", m)
        q, lam, mu, u = w[:n], w[n:n + l], w[n + l:n + l + p], w[n + l + p:]

        def sub(e):
            return ca.substitute([ca.SX(e)], [md.q, md.v, md.theta], [q, ca.SX.zeros(n), th])[0]

        bal = sub(md.f) + ca.mtimes(sub(md.B), u)
        if l:
            bal = bal + ca.mtimes(sub(md.G).T, lam)
        if p:
            bal = bal + ca.mtimes(sub(md.J).T, mu)
        R = ca.vertcat(sub(md.g) if l else ca.SX(0, 1), sub(md.j) if p else ca.SX(0, 1), sub(md.h) - y, bal)
        dR = ca.Function("equilibrium_sens", [w, y, th], [ca.jacobian(R, w), ca.densify(ca.jacobian(R, th))])
        fns = servo.derived["sensitivity"] = (dF, dR)
    return fns


def _factor(tr, J):
    band = tr.banded_pattern()
    if band is not None and band.worthwhile:
        return band.factor(J.data)
    return spl.splu(J.tocsc(), permc_spec="COLAMD")


class ParametricInverse:
    """A solved stable inverse with its collocation system (see the module doc).

    Build it with :meth:`solve` (runs :func:`~invctl.inversion.invert`) or :meth:`from_inverse`
    (from an :class:`Inverse` that ``invert`` returned for ``model`` and ``reference``).

    Attributes
    ----------
    model, reference : the model and ``y_ref`` of this solution
    inverse : Inverse
    x, p : arrays, the collocation unknowns and parameters (``g(x, p) = 0``)
    E0, Ef : arrays, the equilibria at ``T0`` and ``Tf``
    """

    def __init__(self, model, reference, inverse: Inverse, *, servo, selection: Selection, t_mesh, x, p, E0, Ef,
                 newton_tol: float = 1e-10):
        self.model, self.reference, self.inverse = model, reference, inverse
        self.servo, self.selection = servo, selection
        self.scheme = get_scheme(inverse.scheme)
        self.t_mesh, self.x, self.p = np.asarray(t_mesh, float), np.asarray(x, float), np.asarray(p, float)
        self.E0, self.Ef = np.asarray(E0, float), np.asarray(Ef, float)
        self.newton_tol = float(newton_tol)
        self.compiled = "auto"  # of the transcription: True compiles (C, disk-cached), "auto" only reuses the cache
        self._lu = None
        self._lu_at_solution = None
        self._modes: dict = {}
        self._base_modes: dict | None = None

    # ------------------------------------------------------------ construction
    @classmethod
    def solve(cls, model, reference, **invert_options) -> "ParametricInverse":
        """:func:`~invctl.inversion.invert` with ``invert_options``, kept with its collocation system."""
        from .solver import invert

        return cls.from_inverse(model, reference, invert(model, reference, **invert_options))

    @classmethod
    def from_inverse(cls, model, reference, inverse: Inverse, *, check: float = 1e-6) -> "ParametricInverse":
        """Rebuild the collocation system of ``inverse`` (as ``invert`` returned it for ``model``,
        ``reference``): same transcription, mesh, equilibria and boundary selection.

        Raises
        ------
        InversionFailed
            The rebuilt system is not solved by ``inverse`` (residual above ``check``): the inverse
            belongs to another model, reference or parameters.
        """
        d = inverse.diagnostics
        missing = [k for k in ("selection", "formulation", "omega") if k not in d]
        if missing:
            raise InversionFailed(f"the inverse lacks the diagnostics {missing} that invert() records; recompute "
                                  "it with invctl.inversion.invert")
        servo = servo_model(model, d["formulation"], d["omega"])
        sel = _selection(servo, d["selection"])
        if len(sel.start) + len(sel.end) != servo.layout.nx:
            raise InversionFailed("parameter sensitivities need a square inverse (2n + l + p + m boundary "
                                  f"conditions); this one has {len(sel.start) + len(sel.end)} of {servo.layout.nx}")
        obj = cls(model, reference, inverse, servo=servo, selection=sel, t_mesh=inverse.t_mesh, x=np.zeros(0),
                  p=np.zeros(0), E0=inverse.X(inverse.T0)[:, 0], Ef=inverse.X(inverse.Tf)[:, 0])
        tr = obj.transcription()
        Y, yends = obj._samples(reference, obj.t_mesh)
        eq, th = equilibrium_solver(model), model.theta_values
        obj.E0 = eq.solve(yends[:, 0], guess_w=obj._w(obj.E0), theta=th, where=f" at T0 = {inverse.T0}")[0]
        obj.Ef = eq.solve(yends[:, 1], guess_w=obj._w(obj.Ef), theta=th, where=f" at Tf = {inverse.Tf}")[0]
        obj.x = tr.pack(inverse.X_mesh, inverse.X_col)
        obj.p = tr.parameters(obj.t_mesh, Y, th, obj.E0, obj.Ef)
        obj._base_modes = obj._mode_counts(obj.servo, obj.E0, obj.Ef, yends, th)[0]
        res = float(np.max(np.abs(tr.evaluators()[0](obj.x, obj.p))))
        if not res <= check:
            raise InversionFailed(
                f"the inverse does not solve its collocation system for model {model.name!r} with these parameters "
                f"and this reference (max residual {res:.3g} > {check:.1g}): pass the model and reference it was "
                "computed for", diagnostics={"residual": res})
        return obj

    def transcription(self, compiled=None):
        """The collocation system (``compiled``: default :attr:`compiled`)."""
        compiled = self.compiled if compiled is None else compiled
        tr = transcription(self.servo, self.selection, self.scheme, self.t_mesh.size - 1, 0.0, compiled=compiled)
        tr.start_background_compile()
        return tr

    def _w(self, E):
        n = self.model.n
        return np.concatenate([E[:n], E[2 * n:]])

    def _samples(self, reference, t_mesh):
        """Reference samples at the transcription's sample times and ``y_ref`` at ``T0``, ``Tf``."""
        tr = self.transcription()
        ts = tr.sample_times(t_mesh)
        Yall = self.servo.reference_samples(reference, np.concatenate([ts, t_mesh[[0, -1]]]))
        m = self.servo.layout.m
        return Yall[:, :-2], Yall[:m, -2:]

    # ------------------------------------------------------------ re-solve
    def mesh_for(self, reference) -> np.ndarray:
        """The mesh of this solution carried over to ``reference``'s transition ``[t0, tf]``: the
        pre- and post-actuation spans ``t0 - T0``, ``Tf - tf`` are kept, every interval keeps its
        place in its span."""
        inv, r = self.inverse, reference
        if not r.tf > r.t0:
            raise ValueError(f"the reference's transition needs tf > t0, got [{r.t0}, {r.tf}]")
        src = [inv.T0, inv.t0, inv.tf, inv.Tf]
        dst = [r.t0 - (inv.t0 - inv.T0), r.t0, r.tf, r.tf + (inv.Tf - inv.tf)]
        if np.allclose(src, dst, rtol=0, atol=1e-14):
            return self.t_mesh.copy()
        return mapped_mesh(self.t_mesh, src, dst)

    def resolve(self, model=None, reference=None, *, x0=None, guess=None, tol: float | None = None,
                max_iter: int = 30, residual_tol: float = 1e-4, check_modes: bool = True,
                warm: bool = True) -> "ParametricInverse":
        """Solve the same collocation system for other parameters (``model``: same structure,
        e.g. ``model.with_params(m3=0.6)``) and/or another reference (same number of outputs),
        by Newton's method from this solution (or ``x0``; ``warm=False``: from the quasi-static
        guess).  The mesh follows the reference's transition (:meth:`mesh_for`).

        Raises
        ------
        InversionFailed
            Newton did not converge or the result violates the position-level constraints by
            more than ``residual_tol`` (the last iterate is in ``exc.partial``).
        BoundaryConditionError
            The boundary selection no longer matches the modes at the new equilibria.
        """
        t_start = time.perf_counter()
        model = self.model if model is None else model
        reference = self.reference if reference is None else reference
        if model is not self.model and model_key(model) != model_key(self.model):
            raise ValueError(f"resolve: model {model.name!r} has another structure than the one solved (other "
                             "equations, not only other parameter values); use invctl.inversion.invert")
        if reference.m != self.servo.layout.m:
            raise ValueError(f"resolve: the reference has {reference.m} components, the model {self.servo.layout.m}")
        reference.require(3, "servo-constraint inversion (jerk-level index reduction of 003 (35))")
        servo = self.servo  # the same structure: its functions take the parameter values as an argument
        tr = self.transcription()
        t_mesh = self.mesh_for(reference)
        Y, yends = self._samples(reference, t_mesh)
        eq, th, n = equilibrium_solver(model), model.theta_values, model.n
        g0, gf = guess if guess is not None else (self.E0, self.Ef)
        how = "given" if x0 is not None else ("continuation" if warm else "quasi-static")
        if not warm and x0 is None:
            T0, Tf = t_mesh[0], t_mesh[-1]
            qs_t = np.unique(np.concatenate([np.linspace(T0, Tf, 21), np.linspace(reference.t0, reference.tf, 41)]))
            qs_t = qs_t[np.r_[True, np.diff(qs_t) > 1e-9 * (Tf - T0)]]
            G = quasi_static_guess(model, reference, qs_t, np.asarray(g0, float)[:n], servo=servo)
            tc = tr.collocation_times(t_mesh)

            def interp(tt):
                return np.vstack([np.interp(tt, qs_t, row) for row in G])

            x0 = tr.pack(interp(t_mesh), interp(tc) if tc.size else None)
            g0, gf = G[:, 0], G[:, -1]
        E0 = eq.solve(yends[:, 0], guess_w=self._w(np.asarray(g0, float)), theta=th, where=f" at T0 = {t_mesh[0]}")[0]
        Ef = eq.solve(yends[:, 1], guess_w=self._w(np.asarray(gf, float)), theta=th, where=f" at Tf = {t_mesh[-1]}")[0]
        modes = self._check_modes(servo, E0, Ef, yends, th) if check_modes else None
        p = tr.parameters(t_mesh, Y, th, E0, Ef)
        x, info = _newton(tr, self.x if x0 is None else x0, p, lu=self._lu,
                          tol=self.newton_tol if tol is None else tol, max_iter=max_iter)
        self._lu = getattr(tr, "_lu", self._lu) if info["success"] else self._lu
        inv = self._make_inverse(servo, reference, tr, t_mesh, x, Y, th)
        res = self._position_residual(servo, tr, inv, Y, th)
        inv.diagnostics.update(info)
        inv.diagnostics.update({
            "backend": "newton", "scheme": self.scheme.name, "N": int(t_mesh.size - 1),
            "formulation": servo.formulation, "omega": servo.omega, "selection": self.selection.describe(),
            "T0": float(t_mesh[0]), "Tf": float(t_mesh[-1]), "residuals": {"position_mesh": res, "position": res},
            "initial_guess": how, "solve_s": time.perf_counter() - t_start, "build_s": 0.0,
            "modes": modes})
        if not info["success"] or not res <= residual_tol:
            why = (f"Newton: {info['status']} after {info['iterations']} iterations, max constraint violation "
                   f"{info['max_constraint_violation']:.3g}" if not info["success"] else
                   f"position-level constraint residual {res:.3g} > residual_tol = {residual_tol:.3g}")
            raise InversionFailed(f"re-solve of the stable inversion ({how} start) failed: {why}. Try a start closer "
                                  "to this problem (smaller parameter or reference steps), warm=False, or a full "
                                  "invctl.inversion.invert", partial=inv, diagnostics=inv.diagnostics)
        out = ParametricInverse(model, reference, inv, servo=servo, selection=self.selection, t_mesh=t_mesh, x=x,
                                p=p, E0=E0, Ef=Ef, newton_tol=self.newton_tol)
        out._lu, out._modes, out._base_modes = self._lu, self._modes, self._base_modes
        return out

    def _check_modes(self, servo, E0, Ef, yends, th) -> dict:
        """The boundary selection still matches the modes at the new equilibria: as many modes decaying
        forward at ``E0`` and growing at ``Ef`` (eigenvalues of the linearized inverse model) as for the
        checked base solution; otherwise the full :func:`~invctl.inversion.boundary.dichotomy` explains."""
        got, Yend = self._mode_counts(servo, E0, Ef, yends, th)
        if got != self._base_modes:
            dich = dichotomy(servo, self.selection, E0, Yend[:, :1], Ef, Yend[:, 1:], th)
            detail = {k: v for k, v in dich.items() if not k.startswith("eigenvalues")}
            if dich["well_posed"] is False or dich["neutral_internal"]:
                raise BoundaryConditionError(explain_dichotomy(dich, self.selection), diagnostics=detail)
        return got

    def _mode_counts(self, servo, E0, Ef, yends, th):
        Yend = np.zeros((4 * servo.layout.m, 2))
        Yend[:servo.layout.m] = yends
        keys = [(side, E.tobytes(), Yend[:, side].tobytes(), th.tobytes()) for side, E in ((0, E0), (1, Ef))]
        if any(key not in self._modes for key in keys):  # both Jacobians in one buffered (compiled) call
            nx = servo.layout.nx
            J = self.transcription().mapped_call("rhs_jac", 2)(np.column_stack([E0, Ef]), Yend, th)[1]
            ev = np.linalg.eigvals(J.reshape(nx, 2, nx).transpose(1, 0, 2))
            if len(self._modes) > 64:
                self._modes.clear()
            for key, e in zip(keys, ev):
                self._modes[key] = (int(np.sum(e.real < -1e-3)), int(np.sum(e.real > 1e-3)))
        counts = [self._modes[key] for key in keys]
        return {"decaying": counts[0][0], "growing": counts[1][1]}, Yend

    def _make_inverse(self, servo, reference, tr, t_mesh, x, Y, th) -> Inverse:
        Xmesh, Xcol = tr.unpack(x)
        N = t_mesh.size - 1  # slopes: the transcription's (possibly compiled) right-hand side at the mesh
        dX = self.scheme.mesh_slopes(Xmesh, lambda: tr.mapped_call("rhs", N + 1)(Xmesh, Y[:, :N + 1], th)[0])
        return make_inverse(self.model, reference, servo, self.scheme, t_mesh, Xmesh, Xcol, th, dX=dX)

    def _position_residual(self, servo, tr, inv, Y, th) -> float:
        """Largest position-level residual of (35) (``g = 0``, ``h = y_ref``) between the mesh points
        (Hermite-Simpson midpoints, where the interpolant is least accurate; collocation points)."""
        ts = tr.sample_times(inv.t_mesh)
        N = inv.t_mesh.size - 1
        inner = self.scheme.interior_samples(N)
        ts, Y = ts[inner], Y[:, inner]
        pos = tr.mapped_call("residuals", ts.size)(inv.X(ts), Y, th)[0]
        return float(np.max(np.abs(pos))) if pos.size else 0.0

    # ------------------------------------------------------------ sensitivities
    def jacobian_factor(self):
        """The factorized Jacobian ``dg/dx`` at this solution (computed once)."""
        if self._lu_at_solution is None:
            tr = self.transcription()
            try:
                self._lu_at_solution = _factor(tr, tr.evaluators()[1](self.x, self.p)[1])
            except RuntimeError as exc:
                raise InversionFailed(f"the collocation Jacobian is singular at the solution ({exc}): no "
                                      "sensitivities (the boundary selection does not determine the inverse)") from None
        return self._lu_at_solution

    def sensitivities(self, names=None, *, derived: bool = True) -> "Sensitivities":
        """``dX/dp`` (all unknowns: ``q, v, lam, mu, u_ff``) for the named parameters (default: all
        of the model's), by the implicit function theorem (module doc); ``derived`` follows derived
        parameters (:func:`parameter_chain`)."""
        t_start = time.perf_counter()
        md, servo = self.model, self.servo
        th = md.theta_values
        names = list(md.params.names) if names is None else [names] if isinstance(names, str) else list(names)
        chain = parameter_chain(md, names, derived=derived)
        nth, n = th.size, md.n
        dF, dR = _functions(servo)
        # equilibria: R(w, y, theta) = 0  ->  dw/dtheta = -R_w^-1 R_theta
        dE = []
        for E, y in ((self.E0, self.reference(self.inverse.T0)), (self.Ef, self.reference(self.inverse.Tf))):
            Rw, Rt = (np.array(a) for a in dR(self._w(E), np.ravel(y), th))
            dw = -np.linalg.solve(Rw, Rt)
            dE.append(np.vstack([dw[:n], np.zeros((n, nth)), dw[n:]]))
        # dg/dtheta (total: through the equilibria too) from the transcription's own interval function (its
        # SX form: the same transcription, compiled or not)
        trs = self.transcription()
        N, o = self.t_mesh.size - 1, trs.N + trs.m4 * trs.nY
        h = np.diff(self.t_mesh)
        Y = np.asarray(self.p[N:o]).reshape(trs.m4, trs.nY, order="F")
        Xm, Xc = trs.unpack(self.x)
        fn = _interval_theta(trs)
        D, Ft = self.scheme.bvp_theta_jacobian(fn, servo.rhs, dF, Xm, Xc, h, Y, th)
        r = D.shape[0]
        sel = self.selection
        gp = np.vstack([D.reshape(r, N, nth).transpose(1, 0, 2).reshape(N * r, nth),
                        -dE[0][list(sel.start)], -dE[1][list(sel.end)]])
        lu = self.jacobian_factor()
        if hasattr(lu, "pattern"):  # banded LU: one back-substitution per parameter
            dx = -np.column_stack([lu.solve(gp[:, j]) for j in range(nth)])
        else:
            dx = -lu.solve(gp)
        tr = self.transcription()
        dXm = np.stack([tr.unpack(dx[:, j])[0] for j in range(nth)])
        dXc = np.stack([tr.unpack(dx[:, j])[1] for j in range(nth)])
        ddX = self.scheme.slope_sensitivities(servo.rhs_jac, Xm, Y, th, dXm, Ft)
        return Sensitivities(self, names, np.array([md.values[k] for k in names]), chain, dXm, ddX, dXc,
                             dE[0], dE[1], time.perf_counter() - t_start)


def _interval_theta(trs) -> ca.Function:
    """``d(defect of one interval)/dtheta`` from the transcription's interval function (its SX form):
    Hermite-Simpson also through the node slopes, ``+ d/dF_a F_theta(a) + d/dF_b F_theta(b)``; kept by
    the transcription."""
    fn = trs.__dict__.get("_interval_theta")
    if fn is None:
        iv, nx, nth = trs.interval_sx, trs.nx, trs.ntheta
        ins = [ca.SX.sym(iv.name_in(i), iv.sparsity_in(i)) for i in range(iv.n_in())]
        defect = iv(*ins)[0]
        th = ins[-1]
        fn = trs.__dict__["_interval_theta"] = trs.scheme.bvp_theta_function(iv, ins, defect, ca.jacobian(defect, th), nx, nth)
    return fn


@dataclass
class Sensitivities:
    """``dX/dp`` of a stable inverse for named parameters (:meth:`ParametricInverse.sensitivities`).

    ``dX_mesh[j]`` (and ``ddX_mesh[j]``, ``dX_col[j]``) are the derivatives of the collocation data
    with respect to ``theta_j`` (the model's parameter column); ``chain`` maps the named
    parameters to ``theta`` (:func:`parameter_chain`).  The trajectories are linear in these data,
    so :meth:`derivative` gives ``d u_ff / d p (t)`` exactly as the derivative of the interpolant.
    """

    base: ParametricInverse = field(repr=False)
    names: list
    values: np.ndarray
    chain: np.ndarray
    dX_mesh: np.ndarray
    ddX_mesh: np.ndarray
    dX_col: np.ndarray
    dE0: np.ndarray
    dEf: np.ndarray
    wall_s: float = 0.0

    def _combine(self, dtheta) -> Inverse:
        inv = self.base.inverse
        w = np.asarray(dtheta, float)
        return Inverse(inv.scheme, inv.t_mesh, np.tensordot(w, self.dX_mesh, 1), np.tensordot(w, self.ddX_mesh, 1),
                       np.tensordot(w, self.dX_col, 1), inv.sizes, inv.t0, inv.tf, inv.names,
                       {"kind": "sensitivity"})

    def derivative(self, name: str) -> Inverse:
        """``dX/d name`` as an :class:`Inverse` (its ``u(t)`` is ``d u_ff / d name``, ``q(t)`` is ``dq/d name``)."""
        if name not in self.names:
            raise ParameterError(f"no sensitivity for {name!r}; computed for {self.names}")
        return self._combine(self.chain[:, self.names.index(name)])

    def u(self, t) -> np.ndarray:
        """``d u_ff / d p`` at times ``t``: shape ``(len(names), m, len(t))``."""
        return np.stack([self.derivative(k).u(t) for k in self.names])

    def q(self, t) -> np.ndarray:
        """``d q / d p`` at times ``t``: shape ``(len(names), n, len(t))``."""
        return np.stack([self.derivative(k).q(t) for k in self.names])

    def dtheta(self, **values) -> np.ndarray:
        """The change of the parameter column for new values of named parameters (first order)."""
        unknown = sorted(set(values) - set(self.names))
        if unknown:
            raise ParameterError(f"no sensitivity for {unknown}; computed for {self.names}")
        dp = np.array([float(values.get(k, v)) - v for k, v in zip(self.names, self.values)])
        return self.chain @ dp

    def predict(self, model=None, **values) -> Inverse:
        """First-order prediction of the inverse for new parameter values (``m3=0.6``) or for a
        model with other parameter values (``model=plant``: every entry of ``theta`` may change),
        without a re-solve: ``X + dX/dtheta dtheta``."""
        base = self.base
        if model is not None:
            if values:
                raise ParameterError("predict: give either model= or parameter values, not both")
            if model_key(model) != model_key(base.model):
                raise ParameterError("predict: the model has another structure than the one differentiated")
            dth = model.theta_values - base.model.theta_values
        else:
            dth = self.dtheta(**values)
        d = self._combine(dth)
        inv = base.inverse
        out = Inverse(inv.scheme, inv.t_mesh, inv.X_mesh + d.X_mesh, inv.dX_mesh + d.dX_mesh, inv.X_col + d.X_col,
                      inv.sizes, inv.t0, inv.tf, inv.names, {"kind": "first-order prediction",
                                                             "dtheta": dth.tolist()}, y_ref_fn=inv.y_ref_fn)
        return out

    def feedforward_change(self, relative: float = 0.1, t=None) -> dict:
        """``max_t |d u_ff / d p| * |relative * p|`` per parameter and input: the first-order change of
        the feedforward for a relative parameter error (``relative`` of each value)."""
        inv = self.base.inverse
        t = np.linspace(inv.T0, inv.Tf, 2001) if t is None else np.asarray(t, float)
        du = self.u(t)
        return {k: (np.max(np.abs(du[j]), axis=1) * abs(relative * v)).tolist()
                for j, (k, v) in enumerate(zip(self.names, self.values))}

    def to_dict(self) -> dict:
        return {"names": list(self.names), "values": self.values.tolist(), "wall_s": self.wall_s,
                "feedforward_change_10pct": self.feedforward_change(0.1)}
