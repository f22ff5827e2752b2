"""Record an in-process episode (`python -m mapex run --record run.mcap`) as an MCAP file.

The same topics as the distributed recorder (`services.record`, mapex.interop.topics),
fed from the explorers after each step instead of from Zenoh: every robot's pose at every
step, its planned path when it changes, the ensemble mean after each re-plan that
predicted, and the observed map and the whole trajectory every `map_every_steps` steps and
at the end (a whole map per step would make a 1000-step file of hundreds of MB, and a
trajectory per step costs time and space quadratic in the run's length). Stamped in
simulation time (`mapex.interop.sim_time`): step t at `DEFAULT_SIM_CLOCK.stamp_ns(t)`. The
rosbag2 bag (`--record`) and the Foxglove file (`--record-foxglove`) are
`mapex.interop.mcap_file.Recordings`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapex.explorer import Explorer
from mapex.interop.mcap_file import Recordings
from mapex.interop.ros_messages import MapFrame
from mapex.interop.sim_time import DEFAULT_SIM_CLOCK
from mapex.interop.topics import Outgoing, RunTopics


@dataclass(frozen=True)
class RecordingConfig:
    """What an in-process recording keeps."""

    map_every_steps: int = 10  # observed map and trajectory at t = 0, k, 2k, ... and at the end


class EpisodeRecording:
    """The MCAP recordings of one in-process run (the bag at `path`, the Foxglove file at
    `foxglove_path`, either may be None): call `step` after every step (a team's explorers
    in robot order), then `close`."""

    def __init__(
        self,
        path: Path | None,
        run: str,
        shape: tuple[int, int],
        resolution_m: float,
        config: RecordingConfig | None = None,
        foxglove_path: Path | None = None,
    ) -> None:
        self.config = config or RecordingConfig()
        self.recording = Recordings(path, foxglove_path)
        frame = MapFrame(*shape, resolution_m)
        self.topics = RunTopics(run, frame, with_foxglove=self.recording.with_foxglove)
        self._last_path: dict[int, bytes] = {}
        self._last_prediction: dict[int, object] = {}
        self._last_t = -1
        self._explorers: Sequence[Explorer] = ()

    def step(self, t: int, explorers: Sequence[Explorer]) -> None:
        """Record the state after step `t`."""
        stamp_ns = DEFAULT_SIM_CLOCK.stamp_ns(t)
        self._last_t, self._explorers = t, explorers
        for k, explorer in enumerate(explorers):
            robot = f"r{k}"
            now = t % self.config.map_every_steps == 0
            self._write(self.topics.pose(robot, tuple(explorer.pose), stamp_ns, now))
            if now:
                self._write(self.topics.observed(robot, explorer.observed, stamp_ns))
            self._plan(k, robot, explorer, stamp_ns)
            self._mean(k, robot, explorer, stamp_ns)

    def close(self) -> str:
        """Record the final observed maps (when the last step did not), at the last step's
        stamp, finish the files and say what was written ('N messages -> PATH' each)."""
        stamp_ns = DEFAULT_SIM_CLOCK.stamp_ns(max(self._last_t, 0))
        if self._last_t % self.config.map_every_steps != 0:
            for k, explorer in enumerate(self._explorers):
                self._write(self.topics.observed(f"r{k}", explorer.observed, stamp_ns))
                self._write([self.topics.trajectory(f"r{k}", stamp_ns)])
        return self.recording.close()

    def _plan(self, k: int, robot: str, explorer: Explorer, stamp_ns: int) -> None:
        path = np.zeros((0, 2), np.int64) if explorer.path is None else explorer.path
        digest = np.asarray(path, dtype=np.int64).tobytes()
        if self._last_path.get(k) != digest:
            self._last_path[k] = digest
            self._write(self.topics.plan(robot, path, stamp_ns))

    def _mean(self, k: int, robot: str, explorer: Explorer, stamp_ns: int) -> None:
        prediction = explorer.prediction
        if prediction is None or not len(prediction.answered):
            return
        if self._last_prediction.get(k) is not prediction:
            self._last_prediction[k] = prediction
            self._write(self.topics.mean(robot, prediction.mean, stamp_ns))

    def _write(self, messages: list[Outgoing]) -> None:
        for outgoing in messages:
            self.recording.write(outgoing)
