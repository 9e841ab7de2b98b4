"""The result of a stable inversion: :class:`Inverse`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import ResultFileError
from ..results import Animated, Curve, Status
from .schemes import get_scheme

_BLOCKS = ("q", "v", "lam", "mu", "u")


@dataclass
class Inverse(Animated):
    """Feedforward and state trajectories of a stable inversion (003 Sect. 4).

    A :class:`~invctl.results.Trajectory` on the mesh: ``t`` is ``t_mesh`` and ``q, v, lam, mu, u``
    are the mesh values, each also callable at any times (``inv.u(t)`` evaluates the polynomial).

    The trajectories are the collocation polynomials themselves: cubic Hermite
    pieces through ``X_mesh`` with slopes ``dX_mesh`` (Hermite-Simpson) or the
    Lagrange polynomials through ``X_mesh[:, k]`` and the ``d`` collocation states
    of interval ``k`` (Legendre, Radau).  Outside ``[T0, Tf]`` they are held
    constant (the equilibria).

    Attributes
    ----------
    t_mesh : (N+1,) array
    X_mesh : (nx, N+1) array, ``X = (q, v, lam, mu, u)``
    dX_mesh : (nx, N+1) array, ``X'`` at the mesh (Hermite-Simpson)
    X_col : (nx, dN) array, collocation states (Legendre, Radau)
    sizes : dict with ``n, l, p, m``
    t0, tf : float
        Start and end of the reference transition (the causal feedforward starts at ``t0``).
    diagnostics : dict
        status, success, iterations, build_s, solve_s, residuals, mesh history, ...
    """

    scheme: str
    t_mesh: np.ndarray
    X_mesh: np.ndarray
    dX_mesh: np.ndarray
    X_col: np.ndarray
    sizes: dict
    t0: float
    tf: float
    names: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    y_ref_fn: Callable | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.t_mesh = np.asarray(self.t_mesh, float)
        self.X_mesh = np.asarray(self.X_mesh, float)
        self.dX_mesh = np.asarray(self.dX_mesh, float)
        self.X_col = np.asarray(self.X_col, float)
        self._scheme = get_scheme(self.scheme)

    # ------------------------------------------------------------ sizes
    @property
    def T0(self) -> float:
        return float(self.t_mesh[0])

    @property
    def Tf(self) -> float:
        return float(self.t_mesh[-1])

    @property
    def N(self) -> int:
        return self.t_mesh.size - 1

    @property
    def nx(self) -> int:
        return self.X_mesh.shape[0]

    def _slice(self, block: str) -> slice:
        n, l, p, m = (self.sizes[k] for k in ("n", "l", "p", "m"))
        starts = {"q": 0, "v": n, "lam": 2 * n, "mu": 2 * n + l, "u": 2 * n + l + p}
        lens = {"q": n, "v": n, "lam": l, "mu": p, "u": m}
        return slice(starts[block], starts[block] + lens[block])

    # ------------------------------------------------------------ interpolation
    def _locate(self, t):
        """Interval index ``k``, its length ``h`` and the local coordinate ``s`` in [0, 1] of the times ``t``
        (clipped to ``[T0, Tf]``)."""
        tc = np.clip(np.atleast_1d(np.asarray(t, float)), self.T0, self.Tf)
        k = np.clip(np.searchsorted(self.t_mesh, tc, side="right") - 1, 0, self.N - 1)
        h = self.t_mesh[k + 1] - self.t_mesh[k]
        return k, h, (tc - self.t_mesh[k]) / h

    def X(self, t) -> np.ndarray:
        """All unknowns at times ``t``: shape ``(nx, len(t))``."""
        k, h, s = self._locate(t)
        return self._scheme.evaluate(self.X_mesh, self.dX_mesh, self.X_col, k, h, s)

    def dX(self, t) -> np.ndarray:
        """Time derivative of :meth:`X` (of the same polynomials; zero outside ``[T0, Tf]``)."""
        t = np.atleast_1d(np.asarray(t, float))
        k, h, s = self._locate(t)
        out = self._scheme.evaluate(self.X_mesh, self.dX_mesh, self.X_col, k, h, s, derivative=True)
        return np.where((t < self.T0) | (t > self.Tf), 0.0, out)

    def extrema(self, row: int, derivative: bool = False) -> np.ndarray:
        """Times of the interior extrema of ``X[row]`` (of its time derivative with ``derivative``)
        on every mesh interval: where a bound on it can be exceeded between the nodes."""
        h = np.diff(self.t_mesh)
        C = self._scheme.coefficients(self.X_mesh, self.dX_mesh, self.X_col, row, h)
        order = 2 if derivative else 1
        n = C.shape[0] - 1 - order  # degree of the derivative (coefficients highest power first)
        if n < 1:
            return np.zeros(0)
        powers = np.arange(C.shape[0] - 1, order - 1, -1)
        D = C[:n + 1] * np.prod([powers - j for j in range(order)], axis=0)[:, None]
        lead = D[0] != 0
        roots = np.full((self.N, n), np.nan, complex)
        if lead.any():  # all intervals at once: the eigenvalues of the companion matrices (as np.roots)
            comp = np.zeros((int(lead.sum()), n, n))
            comp[:, 0, :] = -(D[1:, lead] / D[0, lead]).T
            comp[:, np.arange(1, n), np.arange(n - 1)] = 1.0
            roots[lead] = np.linalg.eigvals(comp)
        for k in np.flatnonzero(~lead):  # a lower degree on this interval
            r = np.roots(D[:, k]) if D[:, k].any() else np.zeros(0)
            roots[k, :r.size] = r
        ok = (np.abs(roots.imag) < 1e-9) & (roots.real > 0) & (roots.real < 1)
        at = np.nonzero(ok)[0]
        return self.t_mesh[at] + roots.real[ok] * h[at]

    def _curve(self, block: str) -> Curve:
        return Curve(self.X_mesh[self._slice(block)], lambda t: self.X(t)[self._slice(block)])

    q = property(lambda self: self._curve("q"), doc="Coordinates ``q(t)``: shape ``(n, len(t))`` (the mesh values; "
                 "call it at any times).")
    v = property(lambda self: self._curve("v"), doc="Velocities ``v(t)``: shape ``(n, len(t))``.")
    lam = property(lambda self: self._curve("lam"), doc="Holonomic multipliers ``lam(t)``: shape ``(l, len(t))``.")
    mu = property(lambda self: self._curve("mu"), doc="Non-holonomic multipliers ``mu(t)``: shape ``(p, len(t))``.")
    u = property(lambda self: self._curve("u"), doc="The non-causal feedforward ``u_ff(t)`` (with pre-/post-actuation): "
                 "``(m, len(t))``.")

    def u_causal(self, t) -> np.ndarray:
        """The causal feedforward of 003 Sect. 6: zero before ``t0``, ``u_bvp(t)`` after."""
        t = np.atleast_1d(np.asarray(t, float))
        return np.where(t[None, :] < self.t0, 0.0, self.u(t))

    def y_ref(self, t) -> np.ndarray | None:
        """The reference the inverse was computed for (``None`` after loading)."""
        if self.y_ref_fn is None:
            return None
        return self.y_ref_fn(t)

    @property
    def success(self) -> bool:
        return bool(self.diagnostics.get("success", False))

    @property
    def status(self) -> Status:
        """``Status.OK`` for a solved inverse, ``Status.FAILED`` for a partial one (the solver's own word is
        :attr:`solver_status`)."""
        return Status.OK if self.success else Status.FAILED

    @property
    def solver_status(self) -> str:
        """The solver's status (``"Solve_Succeeded"``, ...)."""
        return str(self.diagnostics.get("status", "?"))

    @property
    def t(self) -> np.ndarray:
        """The mesh times (the samples of ``q, v, lam, mu, u``)."""
        return self.t_mesh

    @property
    def y(self) -> np.ndarray:
        """The reference output on the mesh (the inverse tracks it exactly); no rows after loading."""
        yr = self.y_ref(self.t_mesh)
        return np.zeros((0, self.t_mesh.size)) if yr is None else yr

    @property
    def message(self) -> str:
        return str(self.diagnostics.get("message", ""))

    @property
    def stats(self) -> dict:
        """Iterations, times, residuals: the diagnostics (one vocabulary with the other results)."""
        return self.diagnostics

    def sample(self, t) -> dict:
        """``q, v, lam, mu, u`` (and ``u_causal``) at times ``t``, shape ``(rows, len(t))``."""
        return {k: getattr(self, k)(t) for k in ("q", "v", "lam", "mu", "u", "u_causal")}

    # ------------------------------------------------------------ output
    def plot(self, ax=None, *, path=None, dt: float | None = None, **options):
        """One figure: feedforward (causal dashed), coordinates, multipliers (``ax``: three axes to draw in;
        ``path``: save it there too). Returns the figure."""
        import matplotlib.pyplot as plt

        from ..results import plot_target

        ax, path = plot_target(ax, path)
        dt = dt or (self.Tf - self.T0) / 1500
        t = np.arange(self.T0, self.Tf + 0.5 * dt, dt)
        if ax is None:
            fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
        else:
            axes = list(np.atleast_1d(ax))
            fig = axes[0].figure
        u, uc = self.u(t), self.u_causal(t)
        for i in range(u.shape[0]):
            nm = self.names.get("u", [f"u{i + 1}"])[i]
            axes[0].plot(t, u[i], label=f"{nm} (non-causal)")
            axes[0].plot(t, uc[i], "--", label=f"{nm} causal")
        axes[0].set_ylabel("feedforward u_ff")
        q = self.q(t)
        for i in range(q.shape[0]):
            axes[1].plot(t, q[i], label=self.names.get("q", [f"q{i + 1}"] * q.shape[0])[i])
        axes[1].set_ylabel("coordinates q")
        lam = self.lam(t)
        for i in range(lam.shape[0]):
            axes[2].plot(t, lam[i], label=f"lam{i + 1}")
        mu = self.mu(t)
        for i in range(mu.shape[0]):
            axes[2].plot(t, mu[i], label=f"mu{i + 1}")
        axes[2].set_ylabel("multipliers lam, mu")
        axes[2].set_xlabel("time t [s]")
        for ax in axes:
            ax.axvspan(self.t0, self.tf, color="0.92", zorder=-1)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, ncol=3, loc="best")
            ax.grid(alpha=0.3)
        status = self.diagnostics.get("status", "?")
        axes[0].set_title(f"stable inversion ({self.scheme}, N={self.N}, {status}); shaded: [t0, tf]")
        fig.tight_layout()
        if path:
            from ..plot import save

            save(fig, path)
        return fig

    _KIND = "Inverse"
    _ARRAYS = ("t_mesh", "X_mesh", "dX_mesh", "X_col")
    _SAMPLES, _UNSAVED, _FINITE = ("t", "y_ref"), ("y_ref_fn",), ("t_mesh", "X_mesh", "dX_mesh", "X_col", "y_ref")

    def to_npz(self, path, dt: float | None = None, meta: dict | None = None):
        """Save ``t, q, v, lam, mu, u, y_ref`` on a uniform grid of step ``dt`` plus the
        collocation data (``t_mesh, X_mesh, dX_mesh, X_col``) needed by :meth:`load`;
        ``meta`` (JSON-able) records where it came from (scene, parameters). Returns the path."""
        dt = float(dt) if dt else (self.Tf - self.T0) / 1000
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        t = np.arange(self.T0, self.Tf + 0.5 * dt, dt)
        X = self.X(t)
        yr = self.y_ref(t)
        return self._write(path, dict(
            t=t, q=X[self._slice("q")], v=X[self._slice("v")], lam=X[self._slice("lam")], mu=X[self._slice("mu")],
            u=X[self._slice("u")], u_causal=self.u_causal(t), y_ref=np.zeros((0, t.size)) if yr is None else yr), meta)

    @classmethod
    def _read(cls, path, kw: dict, version: int) -> dict:
        """Sizes and collocation data checked against each other; the reference interpolated in its samples."""
        t, yr, tm, X = kw.pop("t"), kw.pop("y_ref"), kw["t_mesh"], kw["X_mesh"]
        sizes = kw["sizes"] = {k: int(kw["sizes"].get(k, -1)) for k in ("n", "l", "p", "m")}
        nx = 2 * sizes["n"] + sizes["l"] + sizes["p"] + sizes["m"]
        if min(sizes.values()) < 0 or X.shape != (nx, tm.size):
            raise ResultFileError(f"{path}: sizes {sizes} (nx = {nx}) do not match the stored mesh data "
                                  f"{X.shape}; the file is inconsistent")
        sch = get_scheme(kw["scheme"])
        ncol = sch.n_col(tm.size - 1)
        if (tm.ndim != 1 or tm.size < 2 or np.any(np.diff(tm) <= 0) or kw["dX_mesh"].shape != X.shape
                or (ncol and kw["X_col"].shape != (nx, ncol))):
            raise ResultFileError(f"{path}: inconsistent collocation data (a mesh that is not increasing, or slopes "
                                  f"{kw['dX_mesh'].shape} / collocation states {kw['X_col'].shape} that do not fit "
                                  f"{X.shape} on a {sch.name} mesh)")
        if yr.size:
            kw["y_ref_fn"] = lambda tt: np.vstack([np.interp(np.atleast_1d(tt), t, row) for row in yr])
        return kw
