"""`output.bag: mcap | ros1`: the run's ROS topics written into the run folder, for ros2 bag, rosbag, Foxglove, rosbags.

- mcap: run.mcap, ROS 2 profile: one `ros2msg` schema per type (the definition with its dependencies, as rosbag2's
  MCAP storage writes it) and CDR messages (rosbags' serialiser, the one the bridge sends).
- ros1: run.bag, ROS 1 bag format 2.0 through rosbags' writer (types with their md5 sums and definitions).
Same topics and rates as the bridge (the scene's bridge.topics / bridge.rates when it has a bridge), stamped with
simulated time. Every sample is kept (a file, unlike a network, must not skip), so it writes in the simulation's
thread; at the default rates that is well under a millisecond per simulated second of a coupled run's work.
"""
from __future__ import annotations

from ..observers import Observer
from .messages import MessageBuilder, msgdef
from .sampler import Sampler
from .topics import topic_table


class BagObserver(Observer):
    rate = None

    def __init__(self, kind: str, bridge_config=None):
        if kind not in ("mcap", "ros1"):
            raise ValueError(f"bag kind {kind!r}")
        self.kind, self.bridge_config = kind, bridge_config

    @property
    def key(self) -> str:
        return "BagWriter"

    def start(self, sim, run) -> None:
        topics = [t for t in topic_table(sim.model, self.bridge_config) if not t.inbound]
        self.sampler = Sampler(sim, topics)
        self.builder = MessageBuilder(2 if self.kind == "mcap" else 1)
        suffix = ".mcap" if self.kind == "mcap" else ".bag"
        # a resumed run keeps the first part and writes the rest beside it
        name = "run" if not run.resumed else f"run-resumed-at-step-{sim.step_count}"
        self.path = run.out / f"{name}{suffix}"
        self.count = 0
        if self.kind == "mcap":
            from mcap.writer import Writer

            self._fh = open(self.path, "wb")
            self._writer = Writer(self._fh)
            self._writer.start(profile="ros2", library="opera-taichi")
            schemas: dict[str, int] = {}
            self._channels = {}
            for t in topics:
                if t.type not in schemas:
                    text, _ = msgdef(self.builder.store, t.type, 2)
                    schemas[t.type] = self._writer.register_schema(t.type, "ros2msg", text.encode("utf-8"))
                self._channels[t.name] = self._writer.register_channel(t.name, "cdr", schemas[t.type])
        else:
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self.path)
            self._writer.open()
            self._channels = {t.name: self._writer.add_connection(t.name, t.type, typestore=self.builder.store,
                                                                   callerid="/opera_taichi")
                              for t in topics}

    def sample(self, sim) -> None:
        snap = self.sampler.sample(sim)
        if not snap:
            return
        ns = int(round(sim.t * 1e9))
        for name, (topic, data) in snap.items():
            raw = self.builder.serialize(self.builder.build(topic, data), topic.type)
            if self.kind == "mcap":
                self._writer.add_message(self._channels[name], log_time=ns, data=raw, publish_time=ns,
                                         sequence=self.count)
            else:
                self._writer.write(self._channels[name], ns, raw)
            self.count += 1

    def close(self, sim, status, message) -> None:
        if self.kind == "mcap":
            self._writer.finish()
            self._fh.close()
        else:
            self._writer.close()
