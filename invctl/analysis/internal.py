"""Byrnes-Isidori coordinates and internal dynamics, 003 Sect. 2 and Sect. 3.

Coordinates (11):  ``Phi(x) = (O1, O2, L_F O2, O3, ..., L_F^(r_hat-1) O3, phi(x))``
with ``L_K phi = 0`` (possible by Lemma 2.1) and ``Phi'`` invertible.  Setting
``O1 = O2 = 0`` gives the internal dynamics ``eta' = q(y, y', ..., eta)`` (16).

Two routes to ``q``:

``method="sect2"``
    the Byrnes-Isidori route: solve ``Phi(x) = (0, y, ..., eta)`` for the full
    state ``x`` (Newton on 2n unknowns) and evaluate ``eta' = phi'(x) F(x)``.
``method="sect3"``
    the feasible coordinates of Sect. 3 for position outputs with ``r_hat = 2``:
    ``eta1 = phi1(q)``, ``eta2 = phi2(q) v`` (22); only ``q`` is found by Newton
    from ``theta(q) = (g, h, phi1) = (0, y, eta1)`` (30), the velocity follows
    linearly from (28), and ``eta'`` from (29) and the ``eta2`` equation before (31).

Default coordinates (Lemma 3.1/3.2): ``phi1 = E q`` with ``E^T`` a kernel basis of
``[G; h'](q0)`` at a design point ``q0``; ``phi2 = V^+ (I - M^-1 [J^T G^T B]
Gamma^-1 [J; G; h'])`` (27) with ``V(q) = Pi(q) V0`` a smooth kernel basis of
``[J; G; h'](q)`` (``Pi`` the orthogonal projector onto that kernel, ``V0`` the
kernel basis at ``q0``).  When ``eta2`` has more than :data:`LEMMA32_MAX_DIM` entries and the
directions ``[J^T G^T B]`` are constant, the default is the construction in the proof of Lemma 3.1,
``phi2 = T2^T M(q)`` (``im T2 = ker [J; G; B^T]``): O(n^2) expressions instead of the O(n^4) of the
symbolic pseudo-inverse in (27), the same internal dynamics up to a linear change of ``eta2``.
"""
from __future__ import annotations

from typing import Any

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import CoordinateError, DimensionError, ModelError
from .auxiliary import auxiliary_system, cache_of, consistent_state, eval_batch, region_samples
from .relative_degree import is_position_output, lie_chain, relative_degree

_LK_TOL = 1e-9
_PHI_SINGULAR_TOL = 1e-10
_NEWTON_OPTS = {"abstol": 1e-12, "max_iter": 60, "error_on_fail": True}


@dataclass(frozen=True)
class InternalDynamics:
    """Internal dynamics ``eta' = q(y, y', ..., eta)`` of a model (003 (16) / (31)).

    Attributes
    ----------
    dim : int
        ``2n - r_bar``.
    dim1, dim2 : int
        Sizes of ``eta1 = phi1(q)`` and ``eta2 = phi2(q) v`` (Sect. 3 split;
        ``dim1 = n - l - m``, ``dim2 = n - p - l - m``).
    Phi : casadi.Function
        ``(q, v, theta) -> (xi, eta)`` (11).
    eta : casadi.Function
        ``(q, v, theta) -> eta``.
    rhs : casadi.Function
        Inputs ``y_0 ... y_{r_hat-1}``, ``eta``, ``theta``; output ``eta_dot``.
    state : casadi.Function
        ``(y_0 ..., eta, theta) -> (q, v)``: the state on the constraint manifold
        with these output derivatives and internal state (``Phi^-1(0, y, ..., eta)``).
    point : ndarray
        Design point ``q0`` (Newton start and, for default coordinates, where E is taken).
    checks : dict
        ``max |L_K phi|``, smallest singular value of ``Phi'`` over the samples, ...
    """

    model: Any
    method: str
    dim: int
    dim1: int
    dim2: int
    r_hat: int
    Phi: ca.Function
    eta: ca.Function
    rhs: ca.Function
    state: ca.Function
    point: np.ndarray
    phi_expr: ca.SX
    coordinates: str
    E: np.ndarray | None = None
    checks: dict = field(default_factory=dict)

    def __call__(self, ys, eta, theta=None) -> np.ndarray:
        """Evaluate ``eta'`` at output derivatives ``ys = (y, y', ...)`` and ``eta``."""
        th = self.model.theta_values if theta is None else np.asarray(theta, float)
        args = point_args(self, (ys, eta))
        eta = args.pop("eta")
        try:
            return np.array(self.rhs(**args, eta=eta, theta=th)["eta_dot"]).ravel()
        except RuntimeError as exc:
            raise CoordinateError(
                f"{self.model.name}: could not invert the coordinates at y-derivatives {ys}, eta = {eta} "
                f"(Newton from q0 = {np.round(self.point, 4).tolist()} failed; no consistent configuration with these "
                f"outputs and internal state may exist): {str(exc).splitlines()[-1]}"
            ) from None

    def summary(self) -> str:
        return (f"internal dynamics ({self.method}, {self.coordinates}): dimension {self.dim} "
                f"(eta1: {self.dim1}, eta2: {self.dim2}); max |L_K phi| = {self.checks.get('LK_max', 0):.2g}, "
                f"min sigma(Phi') = {self.checks.get('Phi_sigma_min', float('nan')):.3g}")


def point_args(internal, point) -> dict:
    """Accept ``(ys, eta)`` with ``ys`` an (r_hat, m) array or list of m-vectors."""
    ys, eta = point
    ys = [np.asarray(y, float).ravel() for y in ys]
    if len(ys) != internal.r_hat:
        raise CoordinateError(f"a linearization point needs r_hat = {internal.r_hat} output derivatives, got {len(ys)}")
    m = internal.model.ny
    eta = np.asarray(eta, float).ravel()
    bad = [f"y^({k}) has length {y.size}, expected m = {m}" for k, y in enumerate(ys) if y.size != m]
    if eta.size != internal.dim:
        bad.append(f"eta has length {eta.size}, expected 2n - r_bar = {internal.dim}")
    if bad:
        raise DimensionError(f"{internal.model.name}: point (ys, eta) = {point!r}: " + "; ".join(bad))
    return {**{f"y_{k}": y for k, y in enumerate(ys)}, "eta": eta}


def xi_expression(model, rd=None) -> tuple[ca.SX, list]:
    """The xi part of (11), ordered ``O1, O2, L_F O2, O3, L_F O3, ...``; also the
    list of ``L_F^k O3`` (k < r_hat) blocks."""
    chain = lie_chain(model)
    p, l, m = model.p, model.ell, model.ny
    blocks = [range(0, p), range(p, p + l), range(p + l, p + l + m)]
    parts, out_blocks = [], []
    for b, idx in enumerate(blocks):
        if not len(idx):
            continue
        rs = {chain.r_aux[i] for i in idx}
        if len(rs) != 1:
            raise CoordinateError(
                f"{model.name}: auxiliary outputs of block O{b + 1} have different relative degrees "
                f"{[chain.r_aux[i] for i in idx]}; 003 (11) assumes a common one per block"
            )
        for k in range(rs.pop()):
            part = ca.vertcat(*[chain.chains[i][k] for i in idx])
            parts.append(part)
            if b == 2:
                out_blocks.append(part)
    return ca.vertcat(*parts), out_blocks


def _null_rows(A: np.ndarray, k: int) -> np.ndarray:
    """k orthonormal rows spanning ker A, each signed so its largest entry is positive."""
    if k == 0:
        return np.zeros((0, A.shape[1]))
    N = np.linalg.svd(A)[2][-k:].copy()
    for i in range(N.shape[0]):
        if N[i, np.argmax(np.abs(N[i]))] < 0:
            N[i] = -N[i]
    return N


#: largest eta2 dimension for which the default coordinates use the normalized form (27): its
#: pseudo-inverse (V^T V)^-1 V^T is then at most 3 x 3 (closed-form minors); beyond, (27) grows like
#: n^4 nodes and the momentum form of the proof of Lemma 3.1 (O(n^2) nodes) is used
LEMMA32_MAX_DIM = 3


def _constant_input_directions(model):
    """``[J^T G^T B]`` as a number matrix if it depends on neither ``q`` nor the parameters, else None."""
    Bt = ca.horzcat(model.J.T, model.G.T, ca.SX(model.B))
    if ca.depends_on(Bt, ca.vertcat(model.q, model.theta)):
        return None
    return np.array(ca.DM(ca.evalf(Bt)))


def coordinate_form(model, form: str = "auto") -> str:
    """``"lemma32"`` or ``"momentum"``: which default coordinates ``form`` means for ``model``."""
    if form not in ("auto", "lemma32", "momentum"):
        raise CoordinateError(f"form must be 'auto', 'lemma32' or 'momentum', got {form!r}")
    Bt = _constant_input_directions(model)
    if form == "momentum" and Bt is None:
        raise CoordinateError(f"{model.name}: the momentum coordinates need constant input and constraint "
                              "directions [J^T G^T B] (independent of q and of the parameters); use form='lemma32'")
    if form != "auto":
        return form
    dim2 = model.n - model.p - model.ell - model.ny
    return "momentum" if Bt is not None and dim2 > LEMMA32_MAX_DIM else "lemma32"


def default_coordinates(model, q0, form: str = "auto") -> tuple[ca.SX, np.ndarray]:
    """Lemma 3.1 coordinates ``(E q, phi2(q) v)`` at design point ``q0``; returns (phi, E).

    ``form="lemma32"``: ``phi2`` of (27), normalized by ``phi2 V = I``.  ``form="momentum"``: the
    construction in the proof of Lemma 3.1, ``phi2 = T2^T M(q)`` with ``T2`` an orthonormal basis of
    ``ker [J; G; B^T]`` (constant directions only): the momenta conjugate to the unactuated,
    unconstrained directions.  By Lemma 3.2 both differ by the invertible left factor
    ``T2^T M V``, so the internal dynamics agree up to a linear change of ``eta2``.  ``"auto"``:
    (27) while ``eta2`` has at most :data:`LEMMA32_MAX_DIM` entries, the momentum form beyond.
    """
    aux = auxiliary_system(model)
    n, p, l, m = model.n, model.p, model.ell, model.ny
    H = ca.jacobian(model.h, model.q)
    th = model.theta_values
    GH = ca.Function("GH", [model.q, model.theta], [ca.vertcat(model.G, H)])
    C = ca.vertcat(model.J, model.G, H)
    Cf = ca.Function("C", [model.q, model.theta], [C])
    E = _null_rows(np.array(GH(q0, th)), n - l - m)
    phi1 = ca.mtimes(ca.DM(E), model.q)
    if n - p - l - m == 0:
        return phi1, E
    if coordinate_form(model, form) == "momentum":
        T2 = _null_rows(_constant_input_directions(model).T, n - p - l - m).T
        return ca.vertcat(phi1, ca.mtimes(ca.DM(T2.T), ca.mtimes(model.M, model.v))), E
    V0 = _null_rows(np.array(Cf(q0, th)), n - p - l - m).T
    Pi = ca.SX.eye(n) - ca.mtimes(C.T, ca.solve(ca.mtimes(C, C.T), C))
    V = ca.mtimes(Pi, ca.DM(V0))
    Vdag = ca.solve(ca.mtimes(V.T, V), V.T)
    Gamma = ca.mtimes(C, aux.MinvBt)
    PiK = ca.SX.eye(n) - ca.mtimes(aux.MinvBt, ca.solve(Gamma, C))
    phi2 = ca.mtimes(Vdag, PiK)
    return ca.vertcat(phi1, ca.mtimes(phi2, model.v)), E


def _momentum_tail(model, phi1, T2, qsol, y1, e2, TH):
    """``(eta', v)`` of the momentum coordinates ``eta2 = T2^T M v`` from ``q``, ``y'`` and ``eta2``
    (MX): ``M v = T2 eta2 + Bt beta`` with ``beta`` from ``C v = (-j, 0, y')``, and
    ``eta2' = T2^T (dM/dt v + f)`` (``T2^T Bt = 0`` removes the inputs and multipliers).  One numeric
    factorization of ``M`` per evaluation; nothing symbolic grows beyond O(n^2)."""
    n, l = model.n, model.ell
    H = ca.jacobian(model.h, model.q)
    C = ca.vertcat(model.J, model.G, H)
    Bt = ca.DM(_constant_input_directions(model))
    T2 = ca.DM(T2)
    parts = ca.Function("momentum_parts", [model.q, model.theta], [model.M, C, model.j])
    Mq, Cq, jq = parts(qsol, TH)
    k = C.shape[0]
    Z = ca.solve(Mq, ca.horzcat(Cq.T, ca.mtimes(T2, e2), Bt), "qr")
    w, SB = Z[:, k], Z[:, k + 1:]
    c = ca.vertcat(-jq, ca.MX.zeros(l), y1)
    beta = ca.solve(ca.mtimes(Cq, SB), c - ca.mtimes(Cq, w))
    vsol = w + ca.mtimes(SB, beta)
    vs = ca.SX.sym("v", n)
    d2 = ca.mtimes(T2.T, ca.jtimes(ca.mtimes(model.M, vs), model.q, vs) + ca.substitute(model.f, model.v, vs))
    tail = ca.Function("momentum_tail", [model.q, vs, model.theta],
                       [ca.vertcat(ca.mtimes(ca.jacobian(phi1, model.q), vs), d2)])
    return tail(qsol, vsol, TH), vsol


def _as_expr(model, phi) -> ca.SX:
    expr = phi(model) if callable(phi) else phi
    expr = ca.SX(expr)
    if expr.shape[1] != 1:
        expr = ca.vec(expr)
    own = ca.vertcat(model.q, model.v, model.theta)
    stray = ca.symvar(ca.substitute(expr, own, ca.SX.zeros(own.shape[0])))
    if stray:
        raise CoordinateError(
            f"{model.name}: phi depends on symbols {sorted(x.name() for x in stray)} that are not the model's "
            "q, v or theta (build phi from model.q, model.v, model.theta, e.g. phi = lambda m: m.q[4])")
    return expr


def design_point(model, q0=None, rng=0) -> np.ndarray:
    """A consistent configuration ``q0`` (given, or the first region sample projected on g = 0)."""
    if q0 is not None:
        q0 = np.asarray(q0, float).ravel()
        return consistent_state(model, q0)[0] if model.ell else q0
    qs, _ = region_samples(model, 20, rng)
    for q in qs:
        try:
            qc = consistent_state(model, q)[0]
        except ModelError:
            continue
        if model.region is None or model.region.contains(qc):
            return qc
    raise CoordinateError(f"{model.name}: no consistent design point found in the region; pass point=q0")


def internal_dynamics(model, method: str = "sect3", phi=None, *, point=None, samples: int = 100,
                      rng=0, check_points=None, form: str = "auto") -> InternalDynamics:
    """Internal dynamics of ``model`` by 003 Sect. 2 (``"sect2"``) or Sect. 3 (``"sect3"``).

    Parameters
    ----------
    method : {"sect3", "sect2"}
    phi : SX or callable ``model -> SX``, optional
        Internal coordinates ``eta = phi(q, v)`` (2n - r_bar rows).  For ``sect3`` the first
        ``n - l - m`` rows must depend on ``q`` only and the rest be linear in ``v``.
        Default: Lemma 3.1/3.2 coordinates at ``point`` (``form``, see :func:`default_coordinates`).
    point : array, optional
        Design configuration ``q0`` (Newton start; where ``E`` is taken).
    samples : int
        Region points at which ``L_K phi = 0`` is checked (a given ``phi``) and where ``Phi'`` stays
        invertible is reported (``checks``: the fraction, the smallest singular value, a singular sample).
        ``Phi'`` must be invertible at ``check_points`` and the design point only: internal coordinates
        may be local (Lemma 3.1), so a singular set elsewhere in the region is data, not an error.
    form : {"auto", "lemma32", "momentum"}
        Which default coordinates (ignored when ``phi`` is given).

    Raises
    ------
    CoordinateError
        ``L_K phi != 0`` or ``Phi'`` singular at a point (both named), wrong sizes,
        or Sect. 3 asked for an output that is not a position output with r_hat = 2.
    RelativeDegreeError
        If the relative degree does not exist on the region.
    """
    if method not in ("sect2", "sect3"):
        raise CoordinateError(f"method must be 'sect2' or 'sect3', got {method!r}")
    key = None
    if phi is None or callable(phi):
        key = ("internal", method, phi, form, None if point is None else tuple(np.asarray(point, float).ravel()),
               samples, repr(rng), repr(model.region), tuple(model.theta_values),
               None if check_points is None else repr([np.asarray(c).tolist() for c in check_points]))
        cache = cache_of(model)
        if key in cache:
            return cache[key]
    result = _internal_dynamics(model, method, phi, point, samples, rng, check_points, form)
    if key is not None:
        cache[key] = result
    return result


def _internal_dynamics(model, method, phi, point, samples, rng, check_points, form="auto") -> InternalDynamics:
    # without a declared region, the relative degree is checked around the design point (not on a default box)
    local = [np.asarray(point, float).ravel()] if model.region is None and point is not None else None
    rd = relative_degree(model, samples=samples, rng=rng, points=local)
    if rd.r_hat is None:
        raise CoordinateError(f"{model.name}: outputs have different relative degrees {rd.r_output}; "
                              "003 Sect. 2 needs a common r_hat")
    n, p, l, m = model.n, model.p, model.ell, model.ny
    dim = 2 * n - rd.r_bar
    dim1, dim2 = n - l - m, n - p - l - m
    if method == "sect3" and not (is_position_output(model) and rd.r_hat == 2):
        raise CoordinateError(f"{model.name}: Sect. 3 coordinates need a position output h(q) with r_hat = 2 "
                              f"(here r_hat = {rd.r_hat}); use method='sect2' with your own phi")
    q0 = design_point(model, point, rng)
    E, momentum = None, False
    if phi is None:
        if not (is_position_output(model) and rd.r_hat == 2):
            raise CoordinateError(f"{model.name}: default coordinates need a position output with r_hat = 2; "
                                  "pass phi")
        momentum = dim2 > 0 and coordinate_form(model, form) == "momentum"
        phi_expr, E = default_coordinates(model, q0, "momentum" if momentum else "lemma32")
        coords = ("phi1 = E q (Lemma 3.1), phi2 = T2^T M (momenta, proof of Lemma 3.1)" if momentum
                  else "phi1 = E q (Lemma 3.1), phi2 by Lemma 3.2 (27)")
    else:
        phi_expr = _as_expr(model, phi)
        coords = "user-given phi"
    if phi_expr.shape[0] != dim:
        raise CoordinateError(f"{model.name}: phi has {phi_expr.shape[0]} rows, the internal dynamics have "
                              f"dimension 2n - r_bar = {2 * n} - {rd.r_bar} = {dim}")
    aux = auxiliary_system(model)
    xi, out_blocks = xi_expression(model)
    x = aux.x
    Phi_expr = ca.vertcat(xi, phi_expr)
    Phi = ca.Function("Phi", [model.q, model.v, model.theta], [xi, phi_expr], ["q", "v", "theta"], ["xi", "eta"])
    eta_fn = ca.Function("eta", [model.q, model.v, model.theta], [phi_expr], ["q", "v", "theta"], ["eta"])

    # ---- checks: L_K phi = 0 and Phi' invertible
    LK = aux.lie_K(phi_expr)
    dPhi = ca.jacobian(Phi_expr, x)
    chk = ca.Function("chk", [model.q, model.v, model.theta], [LK, dPhi])
    cps = [(q0, np.zeros(n))] + list(check_points or [])
    qs, vs = region_samples(model, samples, rng, cps)        # the region samples, then the given points
    LKv, dP = eval_batch(chk, qs, vs, theta=model.theta_values)
    lk = np.max(np.abs(LKv), axis=(1, 2)) if LKv.size else np.zeros(qs.shape[0])
    sv = np.linalg.svd(dP, compute_uv=False)
    smin = sv[:, -1] / np.maximum(sv[:, 0], 1.0)
    used = np.arange(qs.shape[0]) >= qs.shape[0] - len(cps)
    # L_K phi = 0: on the region for a given phi, where used for Lemma 3.1's (built at the design point)
    checked = used if phi is None else np.ones_like(used)
    lk = np.where(checked, lk, 0.0)
    checks = {"LK_max": float(lk.max()), "Phi_sigma_min": float(sv[used, -1].min()), "points_checked": qs.shape[0]}
    if samples:
        # coordinates may be local: where on the region Phi' stays invertible is reported (a singular set is
        # data), required only where the coordinates are used (the design point and check_points)
        region = ~used
        k = int(np.argmin(np.where(region, smin, np.inf)))
        checks["Phi_invertible_fraction_region"] = float(np.mean(smin[region] > _PHI_SINGULAR_TOL))
        checks["Phi_sigma_min_region"] = float(sv[region, -1].min())
        checks["Phi_singular_count"] = int(np.sum(smin[region] <= _PHI_SINGULAR_TOL))
        checks["Phi_singular_sample"] = qs[k].tolist() if smin[k] <= _PHI_SINGULAR_TOL else None
    scale = max(1.0, float(np.max(np.abs(dP[checked]))))
    if lk.max() > _LK_TOL * scale:
        k = int(np.argmax(lk))
        raise CoordinateError(
            f"{model.name}: L_K phi != 0 at q = {np.round(qs[k], 5).tolist()}, v = {np.round(vs[k], 5).tolist()} "
            f"(max |phi' K| = {lk[k]:.3g}); the internal dynamics would depend on the input. Choose phi with "
            "phi_2(q) M(q)^-1 [J^T G^T B] = 0 (003 (25)) or use the default coordinates",
            diagnostics={"q": qs[k], "v": vs[k], "LK": float(lk[k])},
        )
    if np.any(smin[used] <= _PHI_SINGULAR_TOL):
        k = int(np.argmin(np.where(used, smin, np.inf)))
        raise CoordinateError(
            f"{model.name}: Phi' is singular at q = {np.round(qs[k], 5).tolist()}, v = {np.round(vs[k], 5).tolist()} "
            f"(smallest singular value {sv[k, -1]:.3g}); these coordinates are not a diffeomorphism there. "
            "Choose other internal coordinates or restrict the operating region",
            diagnostics={"q": qs[k], "v": vs[k], "sigma_min": float(sv[k, -1])},
        )

    # ---- rhs as a CasADi Function (Newton by rootfinder, derivatives by implicit functions)
    r = rd.r_hat
    TH = ca.MX.sym("theta", model.theta.shape[0])
    Y = [ca.MX.sym(f"y_{k}", m) for k in range(r)]
    ETA = ca.MX.sym("eta", dim)
    if method == "sect2":
        target = ca.SX.sym("target", 2 * n)
        res = ca.Function("Phi_res", [x, ca.vertcat(target, model.theta)], [Phi_expr - target])
        rf = ca.rootfinder("Phi_inv", "newton", res, _NEWTON_OPTS)
        tgt = ca.vertcat(ca.MX.zeros(p + 2 * l), *Y, ETA)
        xs = rf(ca.DM(np.concatenate([q0, np.zeros(n)])), ca.vertcat(tgt, TH))
        Lf = ca.Function("Lf_phi", [x, model.theta], [aux.lie_F(phi_expr)])
        eta_dot = Lf(xs, TH)
        qsol, vsol = xs[:n], xs[n:]
    else:
        phi1, phi2v = phi_expr[:dim1], phi_expr[dim1:]
        if ca.jacobian(phi1, model.v).nnz():
            raise CoordinateError(f"{model.name}: Sect. 3 needs eta1 = phi1(q) (first {dim1} rows of phi) "
                                  "independent of v")
        phi2 = ca.jacobian(phi2v, model.v)
        offset = ca.Function("off", [model.q, model.theta], [ca.substitute(phi2v, model.v, ca.SX.zeros(n))])
        if ca.jacobian(ca.vec(phi2), model.v).nnz() or np.any(np.abs(np.array(offset(q0, model.theta_values))) > 1e-12):
            raise CoordinateError(f"{model.name}: Sect. 3 needs eta2 = phi2(q) v linear in v (last {dim2} rows)")
        H = ca.jacobian(model.h, model.q)
        vartheta = ca.vertcat(model.g, model.h, phi1)
        target = ca.SX.sym("target", n)
        res = ca.Function("theta_res", [model.q, ca.vertcat(target, model.theta)], [vartheta - target])
        rf = ca.rootfinder("vartheta_inv", "newton", res, _NEWTON_OPTS)
        qsol = rf(ca.DM(q0), ca.vertcat(ca.MX.zeros(l), Y[0], ETA[:dim1], TH))
    if method == "sect3" and momentum:
        T2 = _null_rows(_constant_input_directions(model).T, dim2).T
        eta_dot, vsol = _momentum_tail(model, phi1, T2, qsol, Y[1], ETA[dim1:], TH)
    elif method == "sect3":
        y1s, e2s = ca.SX.sym("y_1", m), ca.SX.sym("eta2", dim2)
        Cfull = ca.vertcat(model.J, model.G, H, phi2)
        v_expr = ca.solve(Cfull, ca.vertcat(-model.j, ca.SX.zeros(l), y1s, e2s))      # (28)
        sub = lambda e: ca.substitute(e, model.v, v_expr)  # noqa: E731
        eta1_dot = ca.mtimes(ca.jacobian(phi1, model.q), v_expr)                        # (29)
        eta2_dot = sub(ca.mtimes(ca.jacobian(phi2v, model.q), model.v) + ca.mtimes(phi2, aux.Minvf))
        tail = ca.Function("sect3_tail", [model.q, y1s, e2s, model.theta], [ca.vertcat(eta1_dot, eta2_dot), v_expr])
        eta_dot, vsol = tail(qsol, Y[1], ETA[dim1:], TH)
    names = [f"y_{k}" for k in range(r)] + ["eta", "theta"]
    rhs = ca.Function(f"internal_{method}", [*Y, ETA, TH], [eta_dot], names, ["eta_dot"])
    state = ca.Function(f"internal_state_{method}", [*Y, ETA, TH], [qsol, vsol], names, ["q", "v"])
    return InternalDynamics(model, method, dim, dim1, dim2, r, Phi, eta_fn, rhs, state, q0, phi_expr,
                            coords, E, checks)
