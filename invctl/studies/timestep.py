"""Speed versus accuracy of Moreau-Jean time-stepping (000 scenes).

:func:`timestep_study` runs a stepper over a list of time steps and measures
the errors of the first impact times and post-impact velocities against a
reference (closed form or the event-driven simulator), the fitted
convergence slopes, the penetration with and without position projection,
and the steps per second of the compiled loop.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..plot import finish
from .tradeoff_specs import fitted_order


@dataclass
class TimestepStudy:
    """Errors, slopes, penetration and speed over a sweep of time steps."""

    h: np.ndarray
    impact_time_error: np.ndarray
    post_velocity_error: np.ndarray
    penetration: np.ndarray
    penetration_projected: np.ndarray
    steps_per_s: np.ndarray
    slope_time: float
    slope_velocity: float
    reference: str
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}

    def plot(self, path=None):
        """Errors versus h (log-log, fitted slopes), penetration, and steps/s."""
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 3, figsize=(13, 4))
        ax[0].loglog(self.h, self.impact_time_error, "o-", label=f"impact times (slope {self.slope_time:.2f})")
        ax[0].loglog(self.h, self.post_velocity_error, "s-",
                     label=f"post-impact velocities (slope {self.slope_velocity:.2f})")
        ax[0].loglog(self.h, self.h, "k:", lw=0.8, label="h")
        ax[0].set_xlabel("h [s]")
        ax[0].set_title(f"error vs {self.reference}")
        ax[0].legend(fontsize=8)
        ax[1].loglog(self.h, np.maximum(self.penetration, 1e-18), "o-", label="plain Moreau-Jean")
        ax[1].loglog(self.h, np.maximum(self.penetration_projected, 1e-18), "s-", label="with projection")
        ax[1].axhline(1e-10, color="k", ls=":", lw=0.8)
        ax[1].set_xlabel("h [s]")
        ax[1].set_title("max penetration")
        ax[1].legend(fontsize=8)
        ax[2].semilogx(self.h, self.steps_per_s, "o-")
        ax[2].set_xlabel("h [s]")
        ax[2].set_title("compiled loop: steps/s")
        for a in ax:
            a.grid(True, which="both", alpha=0.3)
        return finish(fig, path)


def timestep_study(stepper, stepper_projected, q0, v0, t_end, hs, ref_times, ref_post, *, n_impacts: int = 3,
                   reference: str = "reference", **run_kw) -> TimestepStudy:
    """Sweep ``hs``; errors of the first ``n_impacts`` impacts against ``ref_times``/``ref_post``."""
    hs = np.asarray(hs, float)
    et, ev, pen, penp, sps = [], [], [], [], []
    for h in hs:
        tr = stepper.run(q0, v0, t_end, h, **run_kw)
        ti, _, _, post, _ = tr.impacts()
        k = min(n_impacts, ti.size, len(ref_times))
        if k == 0:
            et.append(np.nan)
            ev.append(np.nan)
        else:
            et.append(float(np.max(np.abs(ti[:k] - ref_times[:k]))))
            ev.append(float(np.max(np.abs(post[:k] - ref_post[:k]))))
        pen.append(tr.max_gap_violation)
        sps.append(tr.stats["steps_per_s"])
        penp.append(stepper_projected.run(q0, v0, t_end, h, **run_kw).max_gap_violation
                    if stepper_projected is not None else np.nan)
    eta, eva = np.array(et), np.array(ev)
    return TimestepStudy(hs, eta, eva, np.array(pen), np.array(penp), np.array(sps), fitted_order(hs, eta),
                         fitted_order(hs, eva), reference)
