"""The replay file (`replay.bin` in the run folder, with `output.replay: true` or `run --replay`): what the viewer needs
to show the run again, frame by frame, written as the run goes.

Layout: a sequence of records, the first the header (the SceneInfo), then one per frame. A record is
    b"OTRP" | kind (b"H" or b"F") | meta length (u32) | data length (u32) | crc32 of meta + data (u32) | meta | data
meta is JSON (time, joints, tool poses and wrenches: small, read without decompressing anything), data the zlib-packed
arrays listed in meta. Particle positions are quantised to uint16 over the soil domain (about 0.1 mm on a 7 m box)
and stored as the difference from the first frame (grains at rest compress to nothing); speeds as float16. Each
record is flushed when written, so a run that diverged or was killed keeps every whole frame; a torn last record is
skipped when read. A resumed run truncates the file to its checkpoint and appends. Needs numpy only (no viser).
"""
from __future__ import annotations

import json
import os
import struct
import time
import zlib
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..observers import Observer
from .frames import Frame, MachineInfo, SceneInfo, ToolInfo, capture, scene_info

REPLAY_FILE = "replay.bin"
MAGIC = b"OTRP"
FORMAT = 1
_HEAD = struct.Struct("<4sc3I")
Q = 65535.0


# ---------------------------------------------------------------------------------------------- records
def _pack(arrays: dict[str, np.ndarray]) -> tuple[list, bytes]:
    listing, parts = [], []
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        listing.append([name, a.dtype.str, list(a.shape)])
        parts.append(a.tobytes())
    return listing, b"".join(parts)


def _unpack(listing: list, raw: bytes) -> dict[str, np.ndarray]:
    out, offset = {}, 0
    for name, dtype, shape in listing:
        dt = np.dtype(dtype)
        n = int(np.prod(shape)) if shape else 1
        out[name] = np.frombuffer(raw, dtype=dt, count=n, offset=offset).reshape(shape)
        offset += n * dt.itemsize
    return out


def _record(kind: bytes, meta: dict, arrays: dict[str, np.ndarray], level: int = 1) -> bytes:
    listing, raw = _pack(arrays)
    meta = dict(meta, arrays=listing)
    m = json.dumps(meta, separators=(",", ":")).encode()
    d = zlib.compress(raw, level)
    crc = zlib.crc32(d, zlib.crc32(m))
    return _HEAD.pack(MAGIC, kind, len(m), len(d), crc) + m + d


class _Box:
    """uint16 quantisation of positions over the soil domain (with a margin for grains at its walls)."""

    def __init__(self, lo, hi):
        margin = 0.05 * (np.asarray(hi, float) - np.asarray(lo, float))
        self.lo = (np.asarray(lo, float) - margin).astype(np.float64)
        self.span = (np.asarray(hi, float) + margin - self.lo).astype(np.float64)

    def encode(self, p: np.ndarray) -> np.ndarray:
        return np.clip(np.rint((p - self.lo) / self.span * Q), 0, Q).astype(np.uint16)

    def decode(self, q: np.ndarray) -> np.ndarray:
        return (q.astype(np.float64) * (self.span / Q) + self.lo).astype(np.float32)


def _floats(a) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float).ravel()]


def _array(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], float)


# ---------------------------------------------------------------------------------------------- writing
class ReplayWriter:
    def __init__(self, path: Path, info: SceneInfo, append_at: int | None = None):
        self.path = Path(path)
        self.info = info
        self.box = _Box(info.domain_min, info.domain_max)
        self.q0 = self.box.encode(info.initial_positions)
        if append_at is not None and self.path.is_file():
            self.fh = open(self.path, "r+b")
            self.fh.truncate(append_at)
            self.fh.seek(append_at)
        else:   # the header is written aside and renamed in: a reader of a live run never sees a torn header
            part = self.path.with_name(self.path.name + ".part")
            self.fh = open(part, "wb")
            try:
                self._write(_header_record(info, self.q0))
                os.replace(part, self.path)
            except BaseException:
                self.fh.close()
                part.unlink(missing_ok=True)
                raise
        self.frames = 0

    def _write(self, record: bytes) -> None:
        self.fh.write(record)
        self.fh.flush()  # into the OS: a killed process keeps every whole record

    def append(self, frame: Frame) -> None:
        q = self.box.encode(frame.positions)
        delta = len(q) == len(self.q0)
        pos = (q - self.q0) if delta else q   # uint16 arithmetic wraps: q0 + delta restores q exactly
        meta = {"t": frame.t, "wall": round(frame.wall, 4), "n": int(len(q)), "delta": delta,
                "machines": {k: {"q": _floats(v["q"]), "q_cmd": _floats(v["q_cmd"]), "base": _floats(v["base"])}
                             for k, v in frame.machines.items()},
                "tools": [_floats(p) for p in frame.tool_poses], "wrench": [_floats(w) for w in frame.tool_wrench]}
        self._write(_record(b"F", meta, {"pos": pos, "speed": frame.speeds.astype(np.float16)}))
        self.frames += 1

    def offset(self) -> int:
        return self.fh.tell()

    def sync(self) -> None:
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def close(self) -> None:
        if not self.fh.closed:
            self.fh.close()


def _header_record(info: SceneInfo, q0: np.ndarray) -> bytes:
    meta = {"format": "opera-taichi replay", "version": FORMAT, "name": info.name, "duration": info.duration,
            "machines": [{"name": m.name, "urdf": m.urdf, "joints": m.joints, "limits": m.limits}
                         for m in info.machines],
            "tools": [{"name": t.name, "owner": t.owner, "link": t.link} for t in info.tools],
            "domain_min": _floats(info.domain_min), "domain_max": _floats(info.domain_max), "beds": info.beds}
    arrays = {"radii": info.radii.astype(np.float32), "masses": info.masses.astype(np.float32), "q0": q0}
    for i, t in enumerate(info.tools):
        arrays[f"tool{i}_v"] = t.vertices.astype(np.float32)
        arrays[f"tool{i}_f"] = t.faces.astype(np.int32)
    return _record(b"H", meta, arrays, level=6)


class ReplayRecorder(Observer):
    """Writes replay.bin at `rate` Hz of simulated time."""

    def __init__(self, rate: float = 10.0):
        self.rate = float(rate)
        self._offset = None
        self.writer = None

    def start(self, sim, run) -> None:
        self._wall0 = time.perf_counter()
        info = scene_info(sim)
        if run.resumed and self._offset is not None:
            info.initial_positions = ReplayReader(run.out / REPLAY_FILE).info.initial_positions
        self.writer = ReplayWriter(run.out / REPLAY_FILE, info,
                                   append_at=self._offset if run.resumed else None)

    def sample(self, sim) -> None:
        self.writer.append(capture(sim, time.perf_counter() - self._wall0))

    def flush(self) -> None:
        self.writer.sync()

    def get_state(self) -> dict:
        return {"offset": self.writer.offset()}

    def set_state(self, state: dict) -> None:
        self._offset = state.get("offset")

    def close(self, sim, status, message) -> None:
        if self.writer is not None:
            self.writer.close()


# ---------------------------------------------------------------------------------------------- reading
class ReplayReader:
    """The frames of a replay file: metadata of every frame in memory, particles decoded on demand."""

    def __init__(self, path: Path):
        self.path = Path(path)
        try:
            self.data = self.path.read_bytes()
        except OSError as exc:
            raise UserError(f"{self.path}: cannot read the replay ({exc.strerror})") from None
        records = list(self._scan())
        if not records or records[0][0] != b"H":
            raise UserError(f"{self.path}: not an opera-taichi replay file")
        kind, meta, start, length = records[0]
        if meta.get("format") != "opera-taichi replay" or meta.get("version") != FORMAT:
            raise UserError(f"{self.path}: replay format {meta.get('version')!r}, this build reads {FORMAT}")
        try:
            self._read_header(meta, start, length)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError, zlib.error) as exc:
            raise UserError(f"{self.path}: a replay header that cannot be read ({type(exc).__name__}: {exc})") \
                from None
        self.frames = [(m, s, n) for k, m, s, n in records[1:] if k == b"F"]
        self.metas = [m for m, _, _ in self.frames]
        self.times = np.array([m["t"] for m in self.metas], float)

    def _read_header(self, meta: dict, start: int, length: int) -> None:
        arrays = self._arrays(meta, start, length)
        self.header = meta
        tools = [ToolInfo(t["name"], t["owner"], t["link"], arrays[f"tool{i}_v"].copy(), arrays[f"tool{i}_f"].copy())
                 for i, t in enumerate(meta["tools"])]
        self.box = _Box(meta["domain_min"], meta["domain_max"])
        self.q0 = arrays["q0"].copy()
        self.info = SceneInfo(
            meta["name"], float(meta["duration"]),
            [MachineInfo(m["name"], m["urdf"], list(m["joints"]), [tuple(x) for x in m["limits"]])
             for m in meta["machines"]],
            tools, _array(meta["domain_min"]), _array(meta["domain_max"]), [tuple(b) for b in meta["beds"]],
            arrays["radii"].copy(), arrays["masses"].copy(), self.box.decode(self.q0))

    def _scan(self):
        data, pos = self.data, 0
        while pos + _HEAD.size <= len(data):
            magic, kind, m_len, d_len, crc = _HEAD.unpack_from(data, pos)
            end = pos + _HEAD.size + m_len + d_len
            if magic != MAGIC or end > len(data):
                return   # a torn last record (the run was killed mid-write) or not a replay at all
            m = data[pos + _HEAD.size: pos + _HEAD.size + m_len]
            d = memoryview(data)[pos + _HEAD.size + m_len: end]
            if zlib.crc32(d, zlib.crc32(m)) != crc:
                return
            try:
                meta = json.loads(m)
            except ValueError:
                return
            if not isinstance(meta, dict) or (kind == b"F" and not isinstance(meta.get("t"), (int, float))):
                return   # (a record no writer of this format makes)
            yield kind, meta, pos + _HEAD.size + m_len, d_len
            pos = end

    def _arrays(self, meta, start, length) -> dict[str, np.ndarray]:
        return _unpack(meta["arrays"], zlib.decompress(self.data[start:start + length]))

    def __len__(self) -> int:
        return len(self.frames)

    def frame(self, i: int) -> Frame:
        meta, start, length = self.frames[i]
        arrays = self._arrays(meta, start, length)
        q = (self.q0 + arrays["pos"]) if meta["delta"] else arrays["pos"]
        machines = self.machines_at(i)
        tools = np.array([_array(p) for p in meta["tools"]]).reshape(-1, 7)
        wrench = np.array([_array(w) for w in meta["wrench"]]).reshape(-1, 6)
        return Frame(float(meta["t"]), float(meta["wall"]), machines, tools, wrench, self.box.decode(q),
                     arrays["speed"].astype(np.float32))

    def machines_at(self, i: int) -> dict:
        """Frame i's joints and base poses, without decoding its particles."""
        return {k: {"q": _array(v["q"]), "q_cmd": _array(v["q_cmd"]), "base": _array(v["base"])}
                for k, v in self.metas[i]["machines"].items()}

    def index_at(self, t: float) -> int:
        """The last frame at or before simulated time t."""
        return int(max(0, np.searchsorted(self.times, t + 1e-9, side="right") - 1))


def open_run(run_dir) -> ReplayReader:
    """The replay of a run folder; one-line UserError for a folder that is no run, unreadable, or has no replay."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"view: {run_dir} is not a folder (give a run folder written by `opera-taichi run`)")
    manifest = run_dir / "manifest.json"
    try:
        data = json.loads(manifest.read_text())
    except FileNotFoundError:
        raise UserError(f"view: {run_dir} is not a run folder (no manifest.json)") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"view: {manifest}: unreadable manifest ({' '.join(str(exc).split())})") from None
    if not isinstance(data, dict) or "scene" not in data:
        raise UserError(f"view: {manifest} is not an opera-taichi run manifest")
    path = run_dir / REPLAY_FILE
    if not path.is_file():
        output = (data.get("scene") or {}).get("output") or {}
        status = data.get("status", "unknown")
        if isinstance(output, dict) and output.get("replay"):
            if status == "done":
                raise UserError(f"view: {run_dir} has no {REPLAY_FILE}, which its run recorded (moved or deleted?)")
            raise UserError(f"view: {run_dir} stopped (status {status}) before its first replay frame was written")
        raise UserError(f"view: {run_dir} was recorded without a replay; run it again with --replay "
                        f"(or output.replay: true)")
    reader = ReplayReader(path)
    if len(reader) == 0:
        raise UserError(f"view: {path} holds no frame")
    reader.status = data.get("status", "unknown")
    return reader
