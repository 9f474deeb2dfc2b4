"""`--ros1` against masters that are not there, not ROS, or frozen: one line and exit 2 at the start, and a run's
end that a frozen master cannot hold (no roscore needed: the masters here are stand-ins)."""
import socket
import threading
import xmlrpc.server
from pathlib import Path

import pytest

from opera_taichi import cli
from opera_taichi.errors import UserError
from opera_taichi.ros import transport_ros1

REPO = Path(__file__).resolve().parent.parent
DIG = str(REPO / "scenes" / "zx120_dig_cycle.yaml")
HANG_GUARD_S = 60   # a call still running after this has hung (the old code waited forever)


def _in_thread(fn):
    """Run fn on a thread; (finished, exception)."""
    box = {}

    def target():
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["exc"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(HANG_GUARD_S)
    return not thread.is_alive(), box.get("exc")


@pytest.fixture
def listener():
    """A TCP port that accepts connections; `reply` (bytes or None: say nothing) is sent to each."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    state = {"reply": None, "conns": []}

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            state["conns"].append(conn)
            if state["reply"] is not None:
                conn.sendall(state["reply"])
                conn.close()

    threading.Thread(target=serve, daemon=True).start()
    yield server.getsockname()[1], state
    server.close()
    for conn in state["conns"]:
        conn.close()


@pytest.mark.parametrize("reply", [None, b"SSH-2.0-OpenSSH_9.2\r\n"], ids=["silent", "not-http"])
def test_a_master_that_does_not_answer_or_is_no_http_is_one_line(monkeypatch, listener, reply):
    port, state = listener
    state["reply"] = reply
    monkeypatch.setenv("ROS_MASTER_URI", f"http://127.0.0.1:{port}")
    finished, exc = _in_thread(transport_ros1.check_master)
    assert finished, "check_master waited for a master that never answers"
    assert isinstance(exc, UserError) and f"127.0.0.1:{port}" in str(exc) and "\n" not in str(exc), exc


@pytest.mark.parametrize("uri", ["http://localhost:abc", "http://127.0.0.1:{xmlrpc}"], ids=["bad-port", "not-ros"])
def test_an_address_that_is_no_master_is_one_line(monkeypatch, uri):
    """A URI with a port that is no number, and an XML-RPC server that is not a ROS master (its getPid answers a
    bare number): both were tracebacks (exit 1)."""
    server = xmlrpc.server.SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False)
    server.register_function(lambda caller: 7, "getPid")
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        monkeypatch.setenv("ROS_MASTER_URI", uri.format(xmlrpc=server.server_address[1]))
        with pytest.raises(UserError, match="--ros1: ") as info:
            transport_ros1.check_master()
        assert "\n" not in str(info.value)
    finally:
        server.shutdown()
        server.server_close()


def test_ros1_keeps_the_scenes_master_address(monkeypatch, capsys, tmp_path):
    """`--ros1 --set bridge.address=URI` looks for the master at URI (the flag had dropped the address and asked
    ROS_MASTER_URI's default, localhost:11311)."""
    monkeypatch.delenv("ROS_MASTER_URI", raising=False)
    rc = cli.main(["run", DIG, "--ros1", "--set", "bridge.address=http://127.0.0.1:1", "--out",
                   str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "ROS_MASTER_URI=http://127.0.0.1:1 " in err and "11311" not in err


def test_a_frozen_master_does_not_hold_the_runs_end():
    """close() unregisters the node from the master; a master whose host froze never answers, and Ctrl-C had then
    kept the run (and its folder's last writes) waiting for ever."""
    release = threading.Event()

    class Frozen:
        def unregister(self):
            release.wait()

    class Watch:
        def close(self):
            pass

    class Rospy:
        def signal_shutdown(self, reason):
            release.wait()

    transport = transport_ros1.Ros1Transport.__new__(transport_ros1.Ros1Transport)
    transport._watch, transport._subs, transport._pubs, transport.rospy = Watch(), [Frozen()], {"/x": Frozen()}, Rospy()
    try:
        finished, exc = _in_thread(transport.close)
        assert finished and exc is None, exc
    finally:
        release.set()
