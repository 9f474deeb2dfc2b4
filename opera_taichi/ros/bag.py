"""`output.bag: mcap | ros1`: the run's ROS topics written into the run folder, for ros2 bag, rosbag, Foxglove, rosbags.

- mcap: run.mcap, ROS 2 profile: one `ros2msg` schema per type (the definition with its dependencies, as rosbag2's
  MCAP storage writes it) and CDR messages (rosbags' serialiser, the one the bridge sends).
- ros1: run.bag, ROS 1 bag format 2.0 through rosbags' writer (types with their md5 sums and definitions).
Same topics and rates as the bridge (the scene's bridge.topics / bridge.rates when it has a bridge), stamped with
simulated time. Every sample is kept (a file, unlike a network, must not skip), so it writes in the simulation's
thread; at the default rates that is well under a millisecond per simulated second of a coupled run's work.

With checkpoints the bag comes in parts: neither format is readable until its writer has finished it (an MCAP's
chunks and index, a ROS 1 bag's index), so the part is finished before each checkpoint and the run goes on in
run-from-step-<n>.mcap|bag (n: the first rigid step it holds; zero-padded, so the parts sort in time order). A run
killed after a checkpoint keeps readable bags up to it. A resumed run deletes the parts begun after its checkpoint
(that stretch is simulated again) and goes on in a new part: together the parts hold every sample once.
"""
from __future__ import annotations

import re
from pathlib import Path

from ..observers import Observer
from .messages import MessageBuilder, msgdef
from .sampler import Sampler
from .topics import topic_table

_LATER_PART = re.compile(r"run-from-step-(\d+)\.(mcap|bag)")


def bag_parts(run_dir: Path, suffix: str = ".mcap") -> list[Path]:
    """A run folder's bag of one kind (`.mcap` or `.bag`), its parts in time order: run<suffix> first."""
    run_dir = Path(run_dir)
    first = [run_dir / f"run{suffix}"] if (run_dir / f"run{suffix}").is_file() else []
    later = sorted(p for p in run_dir.glob(f"run-from-step-*{suffix}") if _LATER_PART.fullmatch(p.name))
    return first + later


class BagObserver(Observer):
    rate = None

    def __init__(self, kind: str, bridge_config=None):
        if kind not in ("mcap", "ros1"):
            raise ValueError(f"bag kind {kind!r}")
        self.kind, self.bridge_config = kind, bridge_config
        self.count = 0
        self._writer = None
        self._saved = None

    @property
    def key(self) -> str:
        return "BagWriter"

    def get_state(self) -> dict:
        return {"count": self.count, "sampler": self.sampler.get_state(), "builder": self.builder.get_state()}

    def set_state(self, state: dict) -> None:
        self._saved = state

    def start(self, sim, run) -> None:
        self.topics = [t for t in topic_table(sim.model, self.bridge_config) if not t.inbound]
        self.sampler = Sampler(sim, self.topics)
        self.builder = MessageBuilder(2 if self.kind == "mcap" else 1)
        saved = self._saved if run.resumed else None
        if saved:
            self.count = int(saved.get("count", 0))
            self.sampler.set_state(saved.get("sampler", {}))
            self.builder.set_state(saved.get("builder") or {})
        self.suffix = ".mcap" if self.kind == "mcap" else ".bag"
        self.out = run.out
        self.path = None
        if run.resumed:  # the parts begun after the checkpoint hold a stretch that is simulated again
            for part in bag_parts(self.out, self.suffix):
                found = _LATER_PART.fullmatch(part.name)
                if found and int(found.group(1)) > sim.step_count:
                    part.unlink()

    def _open(self, step: int) -> None:
        name = "run" if step == 0 else f"run-from-step-{step:09d}"
        self.path = self.out / f"{name}{self.suffix}"
        if self.kind == "mcap":
            from mcap.writer import Writer

            self._fh = open(self.path, "wb")
            self._writer = Writer(self._fh)
            self._writer.start(profile="ros2", library="opera-taichi")
            schemas: dict[str, int] = {}
            self._channels = {}
            for t in self.topics:
                if t.type not in schemas:
                    text, _ = msgdef(self.builder.store, t.type, 2)
                    schemas[t.type] = self._writer.register_schema(t.type, "ros2msg", text.encode("utf-8"))
                self._channels[t.name] = self._writer.register_channel(t.name, "cdr", schemas[t.type])
        else:
            from rosbags.rosbag1 import Writer

            self.path.unlink(missing_ok=True)  # (rosbags refuses to overwrite: a part left by a killed resume)
            self._writer = Writer(self.path)
            self._writer.open()
            self._channels = {t.name: self._writer.add_connection(t.name, t.type, typestore=self.builder.store,
                                                                   callerid="/opera_taichi")
                              for t in self.topics}

    def sample(self, sim) -> None:
        snap = self.sampler.sample(sim)
        if not snap:
            return
        if self._writer is None:
            self._open(sim.step_count)
        ns = int(round(sim.t * 1e9))
        for name, (topic, data) in snap.items():
            raw = self.builder.serialize(self.builder.build(topic, data), topic.type)
            if self.kind == "mcap":
                self._writer.add_message(self._channels[name], log_time=ns, data=raw, publish_time=ns,
                                         sequence=self.count)
            else:
                self._writer.write(self._channels[name], ns, raw)
            self.count += 1

    def _finish(self) -> None:
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        if self.kind == "mcap":
            writer.finish()
            self._fh.close()
        else:
            writer.close()

    def flush(self) -> None:
        """Before a checkpoint: finish this part (readable from now on); the next sample begins the next one."""
        self._finish()

    def close(self, sim, status, message) -> None:
        self._finish()
