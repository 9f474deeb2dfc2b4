"""`--ros1`: a native ROS 1 node (rospy) registered with the master named by ROS_MASTER_URI.

Messages travel as bytes serialised by rosbags (messages.py): each topic's rospy class is a raw-bytes message class
(rospy's own AnyMsg pattern) that carries the real type name, md5 sum and definition, so the master, `rostopic` and
every subscriber see the standard types.

rospy is not on PyPI. Where it is not importable (a virtual environment), the import below appends Debian's
/usr/lib/python3/dist-packages (where `apt-get install ros-core python3-*-msgs` puts it) to sys.path, after the
environment's own packages, at the moment a ROS 1 bridge starts; a sourced ROS setup (PYTHONPATH) needs nothing.
"""
from __future__ import annotations

import os
import sys
import threading
import xmlrpc.client

from ..errors import UserError
from .messages import msgdef

DEBIAN_DIST_PACKAGES = "/usr/lib/python3/dist-packages"
APT_HINT = ("apt-get install ros-core python3-std-msgs python3-sensor-msgs python3-geometry-msgs python3-nav-msgs "
            "python3-rosgraph-msgs python3-tf2-msgs")


def import_rospy():
    try:
        import rospy
    except ImportError:
        if DEBIAN_DIST_PACKAGES not in sys.path and os.path.isdir(DEBIAN_DIST_PACKAGES):
            sys.path.append(DEBIAN_DIST_PACKAGES)
        try:
            import rospy
        except ImportError as exc:
            raise UserError(f"--ros1: rospy (ROS 1) is not installed ({exc}); on Debian: {APT_HINT}") from None
    return rospy


def master_uri() -> str:
    return os.environ.get("ROS_MASTER_URI") or "http://localhost:11311"


MASTER_CHECK_S = 2.0     # wall seconds between asking the master whether it is still there
MASTER_TIMEOUT_S = 2.0   # a probe not answered in this time is a miss; two misses in a row: the master is gone
CLOSE_WAIT_S = 5.0       # the longest a run's end waits for the master to take the node's unregistering


class _TimeoutTransport(xmlrpc.client.Transport):
    """xmlrpc over HTTP with a socket timeout."""

    def __init__(self, timeout: float):
        super().__init__()
        self._timeout = timeout

    def make_connection(self, host):
        conn = super().make_connection(host)
        conn.timeout = self._timeout
        return conn


def check_master() -> None:
    """A one-line error now rather than a node that waits for a master forever (one that accepts the connection
    and never answers too: the probe times out)."""
    uri = master_uri()
    try:
        reply = xmlrpc.client.ServerProxy(uri, transport=_TimeoutTransport(MASTER_TIMEOUT_S)).getPid(
            "/opera_taichi_probe")
    except Exception as exc:  # noqa: BLE001 - refused, timed out, a bad URI, not HTTP, not XML-RPC: no master
        raise UserError(f"--ros1: no ROS master at ROS_MASTER_URI={uri} ({type(exc).__name__}: "
                        f"{' '.join(str(exc).split()) or 'no answer'}); start `roscore` or set ROS_MASTER_URI") \
            from None
    if not (isinstance(reply, (list, tuple)) and len(reply) == 3 and reply[0] == 1):
        raise UserError(f"--ros1: ROS_MASTER_URI={uri} did not answer as a ROS master")


class MasterWatch:
    """Asks the master every MASTER_CHECK_S, on a thread of its own (a host that stopped answering holds only this
    thread), whether it still knows this node, and says once when it stops answering and once when a master answers
    again: rospy carries on silently, and a restarted master does not know the node until the run is restarted."""

    def __init__(self, uri: str, node: str, log, probe=None):
        self.uri, self.node, self._log = uri, node, log
        self._probe = probe or xmlrpc.client.ServerProxy(uri, transport=_TimeoutTransport(MASTER_TIMEOUT_S))
        self._said = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ros1-master-watch", daemon=True)
        self._thread.start()

    def _ask(self) -> bool | None:
        """True: the master knows this node; False: a master answers that does not; None: no answer."""
        try:
            code, _, _ = self._probe.lookupNode("/opera_taichi_probe", self.node)
        except Exception:  # noqa: BLE001 - refused, timed out, not HTTP, not XML-RPC: no master there
            return None
        return code == 1

    def _say(self, text: str) -> None:
        self._said += 1
        self._log(("master", self._said), text)

    def _run(self) -> None:
        misses, state = 0, True   # state: True knows the node, False does not, None gone
        while not self._stop.wait(MASTER_CHECK_S):
            known = self._ask()
            if known is None:
                misses += 1
                if misses == 2 and state is not None:
                    state = None
                    self._say(f"the ROS master at {self.uri} stopped answering: topics already connected keep "
                              f"flowing, but no new node can find this one (restart roscore, then the run)")
                continue
            misses = 0
            if known != state:
                if known:
                    self._say(f"the ROS master at {self.uri} answers again")
                else:
                    self._say(f"a ROS master answers at {self.uri} but does not know this node (a restarted "
                              f"roscore): new subscribers and publishers cannot find it until the run is restarted")
                state = known

    def close(self) -> None:
        self._stop.set()
        self._thread.join(MASTER_TIMEOUT_S + 1.0)   # a probe in flight says its last before the run's summary


class Ros1Transport:
    protocol = "ROS1"
    ros_version = 1

    def __init__(self, store, node_name: str = "opera_taichi", log=None):
        check_master()
        self.rospy = rospy = import_rospy()
        self.store = store
        self._classes: dict[str, type] = {}
        self._pubs: dict[str, object] = {}
        self._subs: list = []
        # no signal handlers: SIGINT/SIGTERM end the run and close its folder (cli.py), not rospy
        rospy.init_node(node_name, anonymous=True, disable_signals=True, argv=[sys.argv[0]])
        self._watch = MasterWatch(master_uri(), rospy.get_name(), log or (lambda key, text: None))

    def _raw_class(self, typename: str) -> type:
        cls = self._classes.get(typename)
        if cls is None:
            text, md5 = msgdef(self.store, typename, 1)
            cls = type(typename.replace("/", "_"), (self.rospy.AnyMsg,),
                       {"_type": typename.replace("/msg/", "/"), "_md5sum": md5, "_full_text": text,
                        "_has_header": False, "__slots__": []})
            self._classes[typename] = cls
        return cls

    def advertise(self, topic: str, typename: str) -> None:
        self._pubs[topic] = self.rospy.Publisher(topic, self._raw_class(typename), queue_size=10, tcp_nodelay=True)

    def subscribe(self, topic: str, typename: str, on_bytes) -> None:
        self._subs.append(self.rospy.Subscriber(topic, self._raw_class(typename), lambda m: on_bytes(m._buff),
                                                queue_size=10, tcp_nodelay=True))

    def publish(self, topic: str, data: bytes) -> None:
        pub = self._pubs[topic]
        msg = pub.data_class()
        msg._buff = data
        pub.publish(msg)

    def close(self) -> None:
        """Unregisters from the master, but waits for it at most CLOSE_WAIT_S: a master that stopped answering
        (its host frozen) must not keep Ctrl-C from ending the run and writing its folder."""
        self._watch.close()

        def leave():
            for s in self._subs:
                s.unregister()
            for p in self._pubs.values():
                p.unregister()
            self.rospy.signal_shutdown("opera-taichi run ended")

        thread = threading.Thread(target=leave, name="ros1-close", daemon=True)
        thread.start()
        thread.join(CLOSE_WAIT_S)
