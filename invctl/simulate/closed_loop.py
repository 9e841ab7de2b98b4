"""Closed-loop simulation of a constrained multibody plant (003 (1)) with feedforward and feedback.

The plant DAE ``q' = v, M v' = f + G^T lam + B u, g(q) = 0`` is reduced to index 1 with
Baumgarte stabilization of the acceleration constraint,

    G a = -(G' v) v - 2 alpha G v - beta^2 g(q),

so drift of ``g`` and ``G v`` decays instead of growing; both are reported.  Plant, controller
(:class:`invctl.control.funnel_nmp.NMPFunnelController` or none), feedforward (sampled causal
``u_ff``, a B-spline of time) and reference form ONE CasADi expression graph that drives CVODES
(BDF, exact Jacobian by AD) over the output grid; cumulative errors are quadratures of the same
integrator; the graph is expanded to SX and, once its generated C (with the Jacobian) is in the disk cache,
CVODES calls that.  The run is split into chunks (one integrator, start time as parameter) so that leaving
the funnel stops it with :class:`~invctl.errors.FunnelViolation` carrying the trajectory so far.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import (FunnelViolation, OptionError, ParameterError, RunInterrupted, SimulationFailed, check_interrupt,
                      INTERRUPT_LIKE, is_interrupt, watch_sigint)
from ..results import Animated, Status, plot_target

#: a level counts as outside the funnel at this ratio (the law clips 1 - phi^2 e^2 at 1e-6)
VIOLATION_RATIO = 1.0 - 5e-7
#: an integrator failure with a level this close to its boundary counts as leaving the funnel
BOUNDARY_RATIO = 0.99
#: most output samples per call of the monitor (~0.05 s of compiled code)
MONITOR_BLOCK = 2000


@dataclass
class ClosedLoopResult(Animated):
    """Trajectory of a closed-loop run (all arrays with time along the last axis).

    ``ratios`` holds ``phi_i,j |e_i,j|`` for every level and ``phi ||e_bar||`` last (``< 1`` inside the
    funnels); ``drift_g``/``drift_Gv`` are ``max |g(q)|`` and ``max |G v|``; ``signals``/``signals_ref``
    hold the scene's extra signals of the output (e.g. the end effector) and ``cumulative_errors`` the
    integrals ``int ||s - s_ref|| dt`` of the output (key ``"output"``) and of every signal.
    ``status`` is ``"ok"``, ``"left_region"`` (ran to the end, but the plant left the model's operating region:
    ``stats["left_region"]``), ``"funnel_violation"`` (truncated at the violation), ``"failed"`` or
    ``"interrupted"``; :attr:`departure` gives the time a run left its region or funnel.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    z: np.ndarray
    u: np.ndarray
    u_ff: np.ndarray
    u_fb: np.ndarray
    y: np.ndarray
    y_ref: np.ndarray
    ratios: np.ndarray
    e_bar: np.ndarray
    phi_bar: np.ndarray
    drift_g: np.ndarray
    drift_Gv: np.ndarray
    cumulative_errors: dict
    wall_s: float
    signals: dict = field(default_factory=dict)
    signals_ref: dict = field(default_factory=dict)
    controller: str = ""
    status: str = "ok"
    message: str = ""
    ratio_names: list = field(default_factory=list)
    q_names: list = field(default_factory=list)
    y_names: list = field(default_factory=list)
    u_names: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    _KIND = "ClosedLoopResult"
    _ARRAYS = ("t", "q", "v", "z", "u", "u_ff", "u_fb", "y", "y_ref", "ratios", "e_bar", "phi_bar", "drift_g",
               "drift_Gv", "wall_s", "controller", "status", "message", "ratio_names", "q_names", "y_names", "u_names")
    _PREFIXED = {"signals": "signal:", "signals_ref": "signal_ref:"}

    @property
    def departure(self):
        """``(t, "left region")`` or ``(t, "left its funnel")`` (the earlier) if the run left the model's
        operating region or its funnel, else ``None``."""
        exit_ = self.stats.get("left_region")
        found = [(float(exit_["t"]), "left region")] if exit_ else []
        if self.status == "funnel_violation" and self.t.size:
            found.append((float(self.t[-1]), "left its funnel"))
        return min(found) if found else None

    @property
    def cumulative_output_error(self) -> float:
        return float(self.cumulative_errors["output"])

    @property
    def output_error(self) -> np.ndarray:
        return np.linalg.norm(self.y - self.y_ref, axis=0)

    def signal_error(self, name: str) -> np.ndarray:
        """``||s(t) - s_ref(t)||`` of a declared signal (``"output"`` for y)."""
        if name == "output":
            return self.output_error
        return np.linalg.norm(self.signals[name] - self.signals_ref[name], axis=0)

    @property
    def max_funnel_ratio(self) -> float:
        return float(np.max(self.ratios)) if self.ratios.size else 0.0

    @property
    def funnel_margin(self) -> float:
        """``1 - max ratio``: how far the worst level stayed from its funnel boundary."""
        return 1.0 - self.max_funnel_ratio if self.ratios.size else float("nan")

    @property
    def max_constraint_drift(self) -> float:
        return float(max(np.max(self.drift_g, initial=0.0), np.max(self.drift_Gv, initial=0.0)))

    @property
    def input_peaks(self) -> np.ndarray:
        return np.max(np.abs(self.u), axis=1)

    def summary(self) -> dict:
        return {"controller": self.controller, "status": self.status, "success": self.success,
                "message": self.message, "t_end": float(self.t[-1]) if self.t.size else 0.0,
                "cumulative_errors": dict(self.cumulative_errors),
                "cumulative_output_error": self.cumulative_output_error,
                "max_funnel_ratio": self.max_funnel_ratio if self.ratios.size else None,
                "funnel_margin": self.funnel_margin if self.ratios.size else None,
                "max_constraint_drift": self.max_constraint_drift,
                "input_peaks": self.input_peaks.tolist(),
                "final_output_error": float(self.output_error[-1]) if self.t.size else None,
                "left_region": self.stats.get("left_region"),
                "wall_s": self.wall_s}

    def to_csv(self, path) -> None:
        """Time series (t, q, v, u, u_ff, u_fb, y, y_ref, signals, funnel ratios) as CSV with a header."""
        def safe(name):
            return re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_")

        qn = self.row_names("q")
        cols = [("t", self.t), *zip(qn, self.q), *((f"d{n}", row) for n, row in zip(qn, self.v))]
        for name in ("u", "u_ff", "u_fb", "y", "y_ref"):
            cols += [(f"{name}{i + 1}", row) for i, row in enumerate(getattr(self, name))]
        for name, arr in self.signals.items():
            cols += [(f"{safe(name)}{i + 1}", row) for i, row in enumerate(arr)]
            cols += [(f"{safe(name)}_ref{i + 1}", row) for i, row in enumerate(self.signals_ref[name][:len(arr)])]
        cols += [(f"ratio_{safe(n)}", row) for n, row in zip(self.ratio_names, self.ratios)]
        np.savetxt(path, np.column_stack([row for _, row in cols]), delimiter=",", header=",".join(n for n, _ in cols),
                   comments="")

    @classmethod
    def _read(cls, path, kw: dict, version: int) -> dict:
        exit_ = kw["stats"].get("left_region")
        if kw["status"] == "ok" and exit_:   # written before such runs had their own status
            kw["status"], kw["message"] = "left_region", _left_region_message(exit_)
        return kw

    def plot(self, ax=None, *, path=None, **options):
        """Outputs, errors, inputs and funnel (one figure; with ``ax``, the generic panels of
        :class:`~invctl.results.Trajectory` in those axes). Returns the figure."""
        ax, path = plot_target(ax, path)
        if ax is not None:
            return self._generic_plot(ax, path=path, fields=options.get("fields", ("y", "u")))
        from ..plot.tracking import plot_run

        return plot_run(self, path)


def _left_region_message(exit_: dict) -> str:
    return f"left the model's region at t = {exit_['t']:.3g} s ({exit_['coordinates']}; region: {exit_['region']})"


def plant_acceleration(model, alpha: float = 20.0, beta: float = 20.0) -> ca.Function:
    """``(q, v, u, theta) -> (a, lam)`` of the Baumgarte-stabilized index-1 system
    ``[M -G^T -J^T; G 0 0; J 0 0] [a; lam; mu] = [f + B u; -G'vv - 2 alpha G v - beta^2 g; -(Jv+j)'v - alpha (J v + j)]``."""
    from ..model.linalg import acceleration_function

    q, v, th = model.q, model.v, model.theta
    u = ca.SX.sym("u", model.m)
    l = model.ell
    Gv = ca.mtimes(model.G, v)
    Jv = ca.mtimes(model.J, v) + model.j
    bias = ca.vertcat(-ca.jtimes(Gv, q, v) - 2 * alpha * Gv - beta**2 * model.g,
                      -ca.jtimes(Jv, q, v) - alpha * Jv)
    # M a = f + B u + [G; J]^T (lam, mu), [G; J] a = bias: Schur complement on the LDL^T factors of M,
    # with the exact Jacobian CVODES needs by the implicit-function rule (invctl.model.linalg)
    acc = acceleration_function("plant_acc_all", q, v, u, th, model.M, model.f + ca.mtimes(model.B, u),
                                ca.vertcat(model.G, model.J), bias)
    qm, vm = ca.MX.sym("q", model.n), ca.MX.sym("v", model.n)
    um, tm = ca.MX.sym("u", model.m), ca.MX.sym("theta", th.numel())
    a, lam_mu = acc(qm, vm, um, tm)
    return ca.Function("plant_acc", [qm, vm, um, tm], [a, lam_mu[:l]], ["q", "v", "u", "theta"], ["a", "lam"])


def sampled_signal(t, values, name="u_ff") -> ca.Function:
    """MX Function of time from samples (cubic B-spline; held constant outside the samples)."""
    t = np.asarray(t, float).ravel()
    vals = np.asarray(values, float).reshape(-1, t.size)
    if t.size < 4 or np.any(np.diff(t) <= 0):
        raise ParameterError(f"{name}: need >= 4 strictly increasing sample times")
    interp = ca.interpolant(name, "bspline", [t], vals.T.ravel())
    tt = ca.MX.sym("t")
    out = ca.if_else(tt < t[0], ca.DM(vals[:, 0]), ca.if_else(tt > t[-1], ca.DM(vals[:, -1]), interp(tt)))
    return ca.Function(name + "_of_t", [tt], [out], ["t"], [name])


class ClosedLoop:
    """Plant + controller + feedforward + reference compiled into one integrator.

    Parameters
    ----------
    plant : Model
        The simulated plant (its parameter values are the integrator's parameter, so the same
        object simulates other plants with ``run(theta=...)``).
    reference : Reference
        ``y_ref``.
    controller : NMPFunnelController, optional
        Feedback; ``None`` for pure feedforward.
    u_ff : (t, values) or casadi.Function, optional
        Causal feedforward samples (shape (m, N)) or an MX Function of ``t``.
    signals : dict, optional
        ``name -> s(y)`` built from CasADi operations (e.g. the end effector); each signal and its
        reference ``s(y_ref)`` are recorded and ``int ||s - s_ref|| dt`` is integrated.
    t_end, dt : float
        Horizon and output step.
    chunks : int
        Integrator calls per run (funnel checks between them).
    rtol, atol, max_num_steps
        CVODES tolerances and the most steps it may take per output step ``dt`` (CLI ``--rtol``, ``--atol``,
        ``--max-steps``).
    """

    def __init__(self, plant, reference, *, controller=None, u_ff=None, signals=None, t_end=2.0, dt=1e-3,
                 chunks=8, baumgarte=(20.0, 20.0), rtol=1e-8, atol=1e-10, name="", max_num_steps=20000):
        if not t_end > 0 or not dt > 0:
            raise ParameterError(f"need t_end > 0 and dt > 0, got t_end={t_end}, dt={dt}")
        try:
            ok = rtol > 0 and atol > 0 and int(max_num_steps) == max_num_steps >= 1
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise OptionError(f"the integrator needs rtol > 0, atol > 0 and an integer max_num_steps >= 1, got "
                                 f"rtol={rtol!r}, atol={atol!r}, max_num_steps={max_num_steps!r}")
        self.rtol, self.atol, self.max_num_steps = float(rtol), float(atol), int(max_num_steps)
        self.plant, self.reference, self.controller = plant, reference, controller
        self.signals, self.name = dict(signals or {}), name
        self.t_end, self.dt = float(t_end), float(dt)
        n_steps = max(1, int(round(self.t_end / self.dt)))
        self.chunks = max(1, min(int(chunks), n_steps))
        self.per_chunk = int(np.ceil(n_steps / self.chunks))
        self.n_steps = self.per_chunk * self.chunks
        self.dt = self.t_end / self.n_steps
        n, m = plant.n, plant.m
        nz = controller.nz if controller is not None else 0
        self.nx, self.nz = 2 * n + nz, nz
        t = ca.MX.sym("t")
        x = ca.MX.sym("x", self.nx)
        theta = ca.MX.sym("theta", plant.theta.numel())
        t_start = ca.MX.sym("t_start")
        q, v, z = x[:n], x[n:2 * n], x[2 * n:]
        tt = t_start + t
        if isinstance(u_ff, ca.Function):
            self.u_ff_fn = u_ff
        elif u_ff is not None:
            self.u_ff_fn = sampled_signal(*u_ff)
        else:
            self.u_ff_fn = None
        uff = self.u_ff_fn(tt) if self.u_ff_fn is not None else ca.MX.zeros(m)
        if controller is not None:
            ufb, ratios, ebar, _, zdot = controller.symbolic(tt, q, v, z)
            phib = controller.phi_bar.function(0)(tt)
        else:
            ufb, ratios, ebar, zdot, phib = ca.MX.zeros(m), ca.MX(0, 1), ca.MX(0, 1), ca.MX(0, 1), ca.MX(0)
        u = uff + ufb
        acc = plant_acceleration(plant, *baumgarte)
        a, lam = acc(q, v, u, theta)
        h = plant.function("h")(q, v, theta)
        yref = reference.function(0)(tt)
        quad = [ca.norm_2(h - yref)]
        sig, sig_ref = [], []
        for fn in self.signals.values():
            s, sr = ca.MX(fn(h)), ca.MX(fn(yref))
            sig.append(s)
            sig_ref.append(sr)
            quad.append(ca.norm_2(s - sr))
        self.n_quad = len(quad)
        self._signal_sizes = [int(s.numel()) for s in sig]
        dae = {"t": t, "x": x, "p": ca.vertcat(theta, t_start), "ode": ca.vertcat(v, a, zdot), "quad": ca.vertcat(*quad)}
        self.dae = dae  # the closed loop's right-hand side (``p`` = theta, start time of the chunk)
        grid = np.linspace(0.0, self.per_chunk * self.dt, self.per_chunk + 1)[1:]
        opts = {"abstol": self.atol, "reltol": self.rtol, "max_num_steps": self.max_num_steps,
                "linear_solver": "csparse", "print_stats": False, "disable_internal_warnings": True}
        compiled = _compiled_dae(dae)  # generated C of the right-hand side and its Jacobian (disk cache), or None
        self.rhs_backend = "vm" if compiled is None else "c"
        rhs = dae if compiled is None else compiled
        opts["expand"] = compiled is None  # the graph as SX: one flat instruction list, no MX call overhead
        try:
            self.integrator = ca.integrator("closed_loop", "cvodes", rhs, 0.0, grid, opts)
        except RuntimeError:  # a graph that does not expand
            opts["expand"] = False
            self.integrator = ca.integrator("closed_loop", "cvodes", rhs, 0.0, grid, opts)
        self.step_integrator = ca.integrator("closed_loop_step", "cvodes", rhs, 0.0, [self.dt], opts)
        G = plant.function("G")(q, theta)
        mon = ca.Function("monitor", [t, t_start, x, theta],
                          [u, uff, ufb, h, yref, ca.vertcat(*sig) if sig else ca.MX(0, 1),
                           ca.vertcat(*sig_ref) if sig_ref else ca.MX(0, 1), ratios,
                           ca.norm_2(ebar) if ebar.numel() else ca.MX(0),
                           phib, ca.norm_inf(plant.function("g")(q, theta)), ca.norm_inf(ca.mtimes(G, v))],
                          ["t", "t_start", "x", "theta"],
                          ["u", "u_ff", "u_fb", "y", "y_ref", "s", "s_ref", "ratios", "e_bar", "phi_bar", "g", "Gv"])
        self.monitor = _fast(mon)
        self._mon_map = {}

    def _mon_buffers(self, N):
        """The monitor mapped over ``N`` columns with numpy arrays bound as its arguments and results (no
        conversion to and from CasADi matrices per call)."""
        fn = self.monitor.map(N)
        buf, run = fn.buffer()
        ins = [np.zeros((fn.size1_in(i), N), order="F") for i in range(fn.n_in())]
        outs = [np.zeros((fn.size1_out(i), N), order="F") for i in range(fn.n_out())]
        for i, a in enumerate(ins):
            buf.set_arg(i, memoryview(a.reshape(-1, order="F")))
        for i, o in enumerate(outs):
            if o.size:
                buf.set_res(i, memoryview(o.reshape(-1, order="F")))
        self._mon_map[N] = (ins, outs, run, buf)
        return self._mon_map[N]

    def _monitor(self, t, X, theta):
        """The monitor's outputs at the columns of ``X``, in blocks of at most :data:`MONITOR_BLOCK` columns (a
        Ctrl-C waits for one block only)."""
        parts = []
        for a in range(0, t.size, MONITOR_BLOCK):
            check_interrupt()
            tb, Xb = t[a:a + MONITOR_BLOCK], X[:, a:a + MONITOR_BLOCK]
            N = tb.size
            ins, outs, run, _ = self._mon_map.get(N) or self._mon_buffers(N)
            ins[0][0], ins[2][:], ins[3][:] = tb, Xb, theta[:, None]
            run()
            parts.append([o.copy() for o in outs])
        if not parts:
            return [np.zeros((self.monitor.size1_out(i), 0)) for i in range(self.monitor.n_out())]
        return [np.hstack(p) for p in zip(*parts)] if len(parts) > 1 else parts[0]

    def run(self, q0, v0=None, theta=None, *, controller_label=None, raise_on_violation=True) -> ClosedLoopResult:
        """Integrate from ``(q0, v0)`` (plant at rest by default) and return the trajectory.

        Raises
        ------
        FunnelViolation
            When a level leaves its funnel (``partial`` = trajectory up to the violation,
            ``diagnostics`` = time, level, ratio, margin).
        SimulationFailed
            When the integrator fails inside the funnel.
        """
        plant = self.plant
        theta = plant.theta_values if theta is None else np.asarray(theta, float)
        q0 = np.asarray(q0, float).ravel()
        v0 = np.zeros(plant.n) if v0 is None else np.asarray(v0, float).ravel()
        z0 = self.controller.z0(q0, v0) if self.controller is not None else np.zeros(0)
        x = np.concatenate([q0, v0, z0])
        wall0 = time.perf_counter()
        Xs, Ts, quad = [x[:, None]], [np.zeros(1)], np.zeros(self.n_quad)
        Ms = [self._monitor(np.zeros(1), x[:, None], theta)]  # the monitor per chunk, reused by the result
        fail = None
        try:
            for c in range(self.chunks):
                check_interrupt()
                ts = c * self.per_chunk * self.dt
                tg = ts + self.dt * np.arange(1, self.per_chunk + 1)
                try:
                    with watch_sigint() as sigint:  # CVODES turns Ctrl-C into a RuntimeError
                        out = self.integrator(x0=x, p=np.concatenate([theta, [ts]]))
                    Xc, qf = np.array(out["xf"]), np.array(out["qf"])
                except RuntimeError as exc:
                    if sigint.seen:
                        raise KeyboardInterrupt from None
                    Xc, tg, qf, fail = self._steps(x, ts, theta, exc)
                Xs.append(Xc)
                Ts.append(tg)
                if isinstance(fail, KeyboardInterrupt):  # during the step-by-step rerun: keep its steps
                    Ms.append(self._monitor(tg, Xc, theta))
                    raise fail
                if sigint.seen:  # CVODES may recover from a right-hand side that raised KeyboardInterrupt
                    raise KeyboardInterrupt
                if Xc.shape[1]:
                    x = Xc[:, -1]
                    quad = quad + np.asarray(qf).reshape(self.n_quad, -1)[:, -1]
                Ms.append(self._monitor(tg, Xc, theta))
                mon_ratios = Ms[-1][7] if Xc.shape[1] and self.controller is not None else None
                if fail is not None or (mon_ratios is not None and mon_ratios.size
                                        and mon_ratios.max() >= VIOLATION_RATIO):
                    break
        except INTERRUPT_LIKE as _exc:  # keep the simulated prefix (complete chunks)
            if not is_interrupt(_exc):
                raise
            k = min(len(Xs), len(Ts), len(Ms))
            T, X = np.concatenate(Ts[:k]), np.hstack(Xs[:k])
            prefix = self._result(T, X, theta, None, time.perf_counter() - wall0, controller_label or self.name,
                                  _stack(Ms[:k]))
            prefix.status, prefix.message = Status.INTERRUPTED, f"interrupted at t = {T[-1]:.4g} s"
            raise RunInterrupted(f"{prefix.controller or 'closed loop'}: interrupted at t = {T[-1]:.4g} s of "
                                 f"{self.t_end:g} s; the simulated prefix is in exc.partial", partial=prefix,
                                 diagnostics={"t": float(T[-1])}) from None
        wall = time.perf_counter() - wall0
        T = np.concatenate(Ts)
        X = np.hstack(Xs)
        mon = _stack(Ms)
        res = self._result(T, X, theta, quad, wall, controller_label or self.name, mon)
        viol = np.nonzero(res.ratios.max(axis=0) >= VIOLATION_RATIO)[0] if res.ratios.size else np.zeros(0, int)
        if viol.size:
            idx = int(viol[0])
            level = int(np.argmax(res.ratios[:, idx]))
            cut = self._result(T[:idx + 1], X[:, :idx + 1], theta, None, wall, res.controller,
                               [o[:, :idx + 1] for o in mon])
            cut.status, cut.message = Status.FUNNEL_VIOLATION, f"left the funnel at t = {T[idx]:.4g} s"
            diag = {"t": float(T[idx]), "level": res.ratio_names[level] if res.ratio_names else level,
                    "ratio": float(res.ratios[level, idx]), "margin": float(1 - res.ratios[level, idx]),
                    "max_ratio_before": float(res.ratios[:, :idx].max()) if idx else float("nan"),
                    "left_region": self._region_exit(cut)}
            cut.stats["left_region"] = diag["left_region"]
            if raise_on_violation:
                raise FunnelViolation(
                    f"{res.controller or 'closed loop'}: the error left the funnel at t = {T[idx]:.4g} s "
                    f"(level {diag['level']}, ratio {diag['ratio']:.6g} >= 1); widen the funnel (larger r, p), "
                    "raise the gains kappa, or add feedforward", partial=cut, diagnostics=diag)
            return cut
        if fail is not None and res.ratios.size and res.ratios[:, -max(2, T.size // 20):].max() >= BOUNDARY_RATIO:
            level = int(np.argmax(res.ratios[:, -1]))
            res.status = Status.FUNNEL_VIOLATION
            res.message = f"reached the funnel boundary at t = {T[-1]:.4g} s; the integrator stopped"
            diag = {"t": float(T[-1]), "level": res.ratio_names[level] if res.ratio_names else level,
                    "ratio": float(res.ratios[:, -1].max()), "margin": float(1 - res.ratios[:, -1].max()),
                    "integrator": str(fail).splitlines()[-1][:200], "left_region": self._region_exit(res)}
            res.stats["left_region"] = diag["left_region"]
            if raise_on_violation:
                raise FunnelViolation(
                    f"{res.controller or 'closed loop'}: the error reached the funnel boundary at t = {T[-1]:.4g} s "
                    f"(level {diag['level']}, ratio {diag['ratio']:.6g}); the gain 1/(1 - phi^2 e^2) grew beyond what "
                    "the integrator can follow. Widen the funnel (larger r, p), raise the gains kappa, or add "
                    "feedforward", partial=res, diagnostics=diag)
            return res
        exit_ = self._region_exit(res)
        if exit_ is not None:
            res.stats["left_region"] = exit_
            res.status, res.message = Status.LEFT_REGION, _left_region_message(exit_)
        if fail is not None:
            res.status, res.message = Status.FAILED, str(fail).splitlines()[-1][:300]
            where = (f"; the plant left the operating region at t = {exit_['t']:.4g} s ({exit_['coordinates']}; "
                     f"{exit_['region']}), where the relative degree and (A1) are not established: the "
                     "mismatch is too large for this controller" if exit_ is not None else self._advice(res))
            raise SimulationFailed(
                f"{res.controller or 'closed loop'}: the integrator failed at t = {T[-1]:.4g} s inside the funnel "
                f"(max ratio {res.max_funnel_ratio if res.ratios.size else float('nan'):.4g}): {res.message}{where}",
                partial=res, diagnostics={"t": float(T[-1]), "left_region": exit_})
        return res

    def _advice(self, res) -> str:
        """Why the integrator stopped inside the funnel and what to try: a finite-time escape (the input grows
        without bound; no integrator setting helps), else the integrator's settings, by option name."""
        settings = (f"rerun with a larger max_num_steps (CLI --max-steps; now {self.max_num_steps} per output step "
                    f"of {self.dt:g} s) or other rtol/atol (--rtol, --atol; now {self.rtol:g}, {self.atol:g})")
        un = np.linalg.norm(res.u, axis=0)
        k = un.size - 1
        if k < 4 or not (un[k] > 2 * un[k - 3] and un[k] > un[:k - 3].max()):
            return f"; the integrator reached its limits: {settings}"
        a1 = ""
        try:  # (A1) along the last output steps: where it fails the feedback pushes the error the wrong way
            from ..control.new_output import a1_margin_along

            sl = slice(max(0, k - 30), k + 1)
            m = a1_margin_along(self.controller, self.controller.model, res.q[:, sl], res.v[:, sl], t=res.t[sl])
            if m.min_eig <= 0:
                a1 = f"; (A1) fails there, lambda_min = {m.min_eig:.3g} at t = {m.t_min:.4g} s: the feedback pushes " \
                     "the error the wrong way"
        except Exception:  # noqa: BLE001 -- a diagnosis only
            pass
        return (f"; |u| grew from {un[k - 3]:.3g} to {un[k]:.3g} in the last {3 * self.dt:.3g} s: the loop escapes in "
                f"finite time{a1}. No integrator setting removes that: slow the transition, start the plant on "
                f"the inverse's trajectory (feedforward, C1-inv) or reduce the mismatch; to rule out the integrator, "
                f"{settings}")

    def _steps(self, x, ts, theta, exc):
        """Re-run a failed chunk step by step (one output step per call) to keep the trajectory up to the
        failure; returns the failure of the step integrator (a ``KeyboardInterrupt`` after a Ctrl-C), or ``None``
        if every step succeeded."""
        cols, tg, qf = [], [], np.zeros(self.n_quad)
        for kstep in range(self.per_chunk):
            t0 = ts + kstep * self.dt
            check_interrupt()
            try:
                with watch_sigint() as sigint:
                    out = self.step_integrator(x0=x, p=np.concatenate([theta, [t0]]))
            except RuntimeError as e2:
                e2 = KeyboardInterrupt() if sigint.seen else e2  # a Ctrl-C is an interruption, not the failure
                return (np.array(cols).T if cols else np.zeros((self.nx, 0))), np.array(tg), qf[:, None], e2
            x = np.array(out["xf"]).ravel()
            qf = qf + np.array(out["qf"]).ravel()
            cols.append(x)
            tg.append(t0 + self.dt)
            if self.controller is not None:
                if self._monitor(np.array([t0 + self.dt]), x[:, None], theta)[7].max() >= VIOLATION_RATIO:
                    return np.array(cols).T, np.array(tg), qf[:, None], None
        return np.array(cols).T, np.array(tg), qf[:, None], None

    def _region_exit(self, res):
        """First time the plant leaves the model's operating region (where r_hat, Gamma and (A1) were
        established), with the coordinates that are out of bounds; ``None`` if it stays inside."""
        region = getattr(self.plant, "region", None)
        if region is None or res.t.size == 0:
            return None
        lo, hi = np.asarray(region.q_lower, float), np.asarray(region.q_upper, float)
        q = res.q
        inside_box = np.all((q > lo[:, None]) & (q < hi[:, None]), axis=0)
        bad = np.nonzero(~inside_box)[0]
        k = int(bad[0]) if bad.size else None
        if k is None:
            step = max(1, q.shape[1] // 400)
            out_ = np.flatnonzero(~region.inside(q[:, ::step].T))
            k = int(out_[0]) * step if out_.size else None
        if k is None:
            return None
        names = self.plant.q_names
        out = [f"{names[i]} = {q[i, k]:.4g}" for i in range(q.shape[0]) if not lo[i] < q[i, k] < hi[i]]
        return {"t": float(res.t[k]), "coordinates": ", ".join(out) or "a region constraint",
                "region": getattr(region, "description", "")}

    def _result(self, T, X, theta, quad, wall, label, mon=None):
        n = self.plant.n
        u, uff, ufb, y, yref, s, sref, ratios, ebar, phib, dg, dgv = self._monitor(T, X, theta) if mon is None else mon
        signals, signals_ref, off = {}, {}, 0
        for name, size in zip(self.signals, self._signal_sizes):
            signals[name], signals_ref[name] = s[off:off + size], sref[off:off + size]
            off += size
        if quad is None:
            errs = [np.linalg.norm(y - yref, axis=0)] + [np.linalg.norm(signals[k] - signals_ref[k], axis=0)
                                                         for k in self.signals]
            quad = [np.trapezoid(e, T) if T.size > 1 else 0.0 for e in errs]
        names = list(self.controller.ratio_names) if self.controller is not None else []
        plant = self.plant
        return ClosedLoopResult(
            t=T, q=X[:n], v=X[n:2 * n], z=X[2 * n:], u=u, u_ff=uff, u_fb=ufb, y=y, y_ref=yref,
            ratios=ratios if self.controller is not None else np.zeros((0, T.size)),
            e_bar=ebar.ravel(), phi_bar=phib.ravel(), drift_g=dg.ravel(), drift_Gv=dgv.ravel(),
            cumulative_errors={"output": float(quad[0]), **{k: float(v) for k, v in zip(self.signals, quad[1:])}},
            wall_s=wall, signals=signals, signals_ref=signals_ref, controller=label, ratio_names=names,
            q_names=list(plant.q_names), y_names=list(plant.y_names), u_names=list(plant.u_names),
            stats={"chunks": self.chunks, "dt": self.dt})


def _fast(fn: ca.Function) -> ca.Function:
    """``fn`` expanded to SX, as compiled C when it is in the disk cache; else the C is built in the background
    for the next run (:mod:`invctl.inversion.compiled`; off with ``INVCTL_BACKGROUND_COMPILE=0``)."""
    from ..inversion.compiled import compile_cached, compile_in_background, is_cached

    try:
        fn = fn.expand()
    except RuntimeError:
        return fn
    try:
        if is_cached(fn):
            return compile_cached(fn)
    except RuntimeError:
        return fn
    compile_in_background([fn])
    return fn


#: instructions (right-hand side and its Jacobian) above which a closed loop is not compiled: the flexible arm's
#: n = 16 loop (2.1e5) builds in 45 s at -O1; n = 32 (millions) ran gcc for over 10 minutes at 6 GB
COMPILE_LIMIT = 1_000_000


def _compiled_dae(dae, wait: bool = False):
    """The closed loop's DAE (expanded to SX) as generated C from the disk cache, with its Jacobian as
    ``jac_<name>`` in the same library (CVODES's Newton iterations use it); ``None`` when it is not there yet:
    then it is generated and a detached, low-priority compiler builds it for the next loop of the same graph
    (as :mod:`invctl.inversion.compiled`; off with ``INVCTL_BACKGROUND_COMPILE=0``), unless the right-hand side
    and its Jacobian exceed ``COMPILE_LIMIT`` instructions. ``wait``: compile now."""
    import hashlib
    import os
    import shutil
    import subprocess
    import tempfile

    from ..inversion.compiled import background_enabled, cache_dir, compiler

    if compiler() is None or os.name != "posix":
        return None
    try:
        fn = ca.Function("cl", [dae["t"], dae["x"], ca.MX.sym("z", 0), dae["p"], ca.MX.sym("u", 0)],
                         [dae["ode"], ca.MX(0, 1), dae["quad"], ca.MX(0, 1)], ca.dyn_in(), ca.dyn_out()).expand()
    except RuntimeError:
        return None
    name = "closed_loop_" + hashlib.sha1(fn.serialize().encode()).hexdigest()[:16]
    lib = cache_dir() / f"{name}.so"
    if lib.exists():
        try:
            return ca.external(name, str(lib))
        except RuntimeError:
            return None
    lock = lib.with_suffix(".lock")
    if not wait and (not background_enabled() or (lock.exists() and time.time() - lock.stat().st_mtime < 600)):
        return None
    fn = ca.Function(name, fn.sx_in(), fn.call(fn.sx_in()), ca.dyn_in(), ca.dyn_out())
    jac = fn.jacobian()  # named jac_<name>: casadi.external finds it
    if fn.n_instructions() + jac.n_instructions() > COMPILE_LIMIT:
        return None  # the virtual machine runs it: compiling would take many minutes and gigabytes
    tmp = tempfile.mkdtemp(prefix="invctl-cl-")
    cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    cg.add(fn)
    cg.add(jac)
    cg.generate(tmp + os.sep)
    lock.write_text(str(os.getpid()))
    part = lib.with_suffix(f".{os.getpid()}.part")
    # -O1: long straight-line code (the Jacobian), which -O3 compiles for much longer
    script = '"$0" -O1 -fPIC -shared -o "$1" "$2" -lm && mv "$1" "$3"; rm -rf "$4"; rm -f "$5" "$1"'
    job = subprocess.Popen((["nice", "-n", "19"] if shutil.which("nice") else []) + [
        "sh", "-c", script, str(compiler()), str(part), os.path.join(tmp, f"{name}.c"), str(lib), tmp, str(lock)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    if wait and job.wait() == 0 and lib.exists():
        return ca.external(name, str(lib))
    return None


def _stack(mons):
    """The monitor's outputs of consecutive pieces joined along time."""
    return [np.hstack(p) for p in zip(*mons)]


def scipy_reference_run(loop: ClosedLoop, q0, v0=None, theta=None, *, method="LSODA", rtol=1e-8, atol=1e-10,
                        u_ff=None):
    """The same closed loop run by ``scipy.integrate.solve_ivp`` with a Python/numpy right-hand side.

    Independent of :class:`ClosedLoop`'s assembly: the plant uses the foundation's index-1 function
    ``Model.accel_and_multipliers`` (no Baumgarte terms), the feedforward a scipy cubic spline of the
    same samples, the controller its compiled ``output``/``state`` Functions called per evaluation.
    Returns ``(t, X, wall_s, nfev)`` on the loop's output grid.
    """
    from scipy.integrate import solve_ivp
    from scipy.interpolate import make_interp_spline

    plant, ctrl = loop.plant, loop.controller
    n = plant.n
    theta = plant.theta_values if theta is None else np.asarray(theta, float)
    acc = plant.accel_and_multipliers
    if u_ff is not None:
        tff, vff = u_ff
        spline = make_interp_spline(np.asarray(tff), np.asarray(vff).T, k=3)
        t_lo, t_hi = float(tff[0]), float(tff[-1])
        uff = lambda t: spline(min(max(t, t_lo), t_hi))  # noqa: E731
    else:
        uff = lambda t: np.zeros(plant.m)  # noqa: E731
    if ctrl is not None:
        state, output, _ = ctrl.functions()
    q0 = np.asarray(q0, float).ravel()
    v0 = np.zeros(n) if v0 is None else np.asarray(v0, float).ravel()
    z0 = ctrl.z0(q0, v0) if ctrl is not None else np.zeros(0)

    def rhs(t, x):
        q, v, z = x[:n], x[n:2 * n], x[2 * n:]
        u = uff(t)
        if ctrl is not None:
            u = u + np.asarray(output(t, q, v, z)).ravel()
            zd = np.asarray(state(t, q, v, z)).ravel()
        else:
            zd = np.zeros(0)
        a = np.asarray(acc(q, v, u, theta)[0]).ravel()
        return np.concatenate([v, a, zd])

    t_eval = np.linspace(0.0, loop.t_end, loop.n_steps + 1)
    wall0 = time.perf_counter()
    sol = solve_ivp(rhs, (0.0, loop.t_end), np.concatenate([q0, v0, z0]), method=method, rtol=rtol, atol=atol,
                    t_eval=t_eval)
    wall = time.perf_counter() - wall0
    if not sol.success:
        raise SimulationFailed(f"scipy reference run failed: {sol.message}", diagnostics={"t": float(sol.t[-1])})
    return sol.t, sol.y, wall, sol.nfev
