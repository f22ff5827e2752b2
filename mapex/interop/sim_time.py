"""Simulation time: the clock every outside tool sees (ROS `/clock`, message stamps, MCAP
log times), so a run replays the same however fast it was computed.

Step t of a run happens at t * `seconds_per_step` seconds of simulated time (the initial
scan, t = 0, at 0 s): with the default 1 s per step and 3 cells of 0.1 m per step, the
robot drives at 0.3 m/s. ROS nodes started with `use_sim_time:=true` take this clock.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapex.config import Checked, positive

NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class SimClock(Checked):
    """How long one step lasts in simulated time."""

    SECTION = "sim_clock"
    seconds_per_step: float = positive(1.0)

    def stamp_ns(self, t: int) -> int:
        """The stamp (ns of simulated time) of step `t`."""
        return int(round(int(t) * self.seconds_per_step * NS_PER_S))


DEFAULT_SIM_CLOCK = SimClock()
