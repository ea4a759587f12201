"""rosbag2 (MCAP storage) reading and writing without ROS, with the project's message types.

Pure module (rosbags, no rclpy): the offline generator, the bag tools and the tests all use it.

- :func:`typestore` registers the docs/interfaces.md messages from the ``.msg`` files of
  ``train_interfaces`` (found through the ament index, else in the source tree), so definitions
  are embedded in every bag written, exactly as a ROS 2 recorder would.
- :class:`BagWriter` writes dict-valued messages (docs/interfaces.md field names) or raw CDR bytes.
  From the start and at every :meth:`BagWriter.flush` the bag on disk is one that readers open:
  ``metadata.yaml`` lists the topics and counts flushed so far, and the MCAP file ends in a
  provisional footer without a summary (readers scan it); :meth:`BagWriter.close` writes the
  final summary and metadata. A writer killed between flushes leaves such a bag.
- :func:`read_bag` reads a bag into per-topic lists of ``(t_recv_ns, stamp_s, fields)``; a bag
  that was never closed (no summary, or no footer at all) is read record by record, up to the
  last complete one.
- :func:`repair_bag` (``python -m train_core.bagio repair BAG``) makes a bag whose recorder was
  killed a normal, indexed bag again (summary, end magic, metadata.yaml).
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path

import numpy as np

PKG = "train_interfaces"
MSG_NAMES = ("OdometerReading", "BaliseReading", "ControlCommand", "TrainState",
             "MovementAuthority")
TOPIC_TYPES = {
    "odometer": "train_interfaces/msg/OdometerReading",
    "balise": "train_interfaces/msg/BaliseReading",
    "control": "train_interfaces/msg/ControlCommand",
    "ground_truth": "train_interfaces/msg/TrainState",
    "estimate/robust": "train_interfaces/msg/TrainState",
    "estimate/gsma": "train_interfaces/msg/TrainState",
    # a second gsma_estimator with algorithm kf (the exact Kalman reference the main job runs
    # beside the GSMA; docs/ros.md)
    "estimate/kf": "train_interfaces/msg/TrainState",
    "movement_authority": "train_interfaces/msg/MovementAuthority",
}
MAGIC = b"\x89MCAP0\r\n"
# DataEnd (op 0x0F, data-section CRC 0 = not computed), then a Footer (op 0x02) with no summary
# (summary start 0, summary-offset start 0, CRC 0) and the end magic: a valid end of an MCAP
# file whose readers scan the data section instead of using an index.
PROVISIONAL_TAIL = (b"\x0f" + (4).to_bytes(8, "little") + bytes(4)
                    + b"\x02" + (20).to_bytes(8, "little") + bytes(20) + MAGIC)
HEADER_DEF = "builtin_interfaces/Time stamp\nstring frame_id\n"
TIME_DEF = "int32 sec\nuint32 nanosec\n"
SEP = "=" * 80 + "\n"


class BagError(RuntimeError):
    """The bag is unreadable or lacks what was asked; the message is one line."""


def msg_dir() -> Path:
    """Where the train_interfaces .msg files are: the installed share dir, else the source."""
    try:
        from ament_index_python.packages import get_package_share_directory

        d = Path(get_package_share_directory(PKG)) / "msg"
        if d.is_dir():
            return d
    except Exception:  # not installed / no ament index: use the source tree
        pass
    d = Path(__file__).resolve().parents[2] / PKG / "msg"
    if d.is_dir():
        return d
    raise BagError(f"cannot find the {PKG} .msg files (build ros_ws or set AMENT_PREFIX_PATH)")


@lru_cache(maxsize=1)
def msg_texts() -> dict[str, str]:
    d = msg_dir()
    return {f"{PKG}/msg/{n}": (d / f"{n}.msg").read_text() for n in MSG_NAMES}


def msgdef(msgtype: str) -> str:
    """The ros2msg definition text embedded in bags (the format rosbag2 writes)."""
    return (msg_texts()[msgtype] + SEP + "MSG: std_msgs/Header\n" + HEADER_DEF + SEP
            + "MSG: builtin_interfaces/Time\n" + TIME_DEF)


@lru_cache(maxsize=1)
def typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name, text in msg_texts().items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


@lru_cache(maxsize=1)
def own_typestore():
    """The docs/interfaces.md messages with only the types they hold (Header, Time): what
    reading a bag decodes. The same definitions, hashes and CDR layout as in :func:`typestore`,
    without building ROS 2's standard message set from its first release on (0.1-0.2 s of every
    ``diagnose``, ``check_bag`` and ``identify`` run); writers keep :func:`typestore`, which
    other types (``nav_msgs``, ``diagnostic_msgs``) need."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.EMPTY)
    types = {}
    types.update(get_types_from_msg(TIME_DEF, "builtin_interfaces/msg/Time"))
    types.update(get_types_from_msg(HEADER_DEF, "std_msgs/msg/Header"))
    for name, text in msg_texts().items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


# TrainState fields later than its first definition, with the value an older writer means
_LATER_FIELDS = {"integrity": 0, "protection_level_ahead": math.inf,
                 "protection_level_behind": math.inf}


def _build(ts, msgtype: str, fields: dict, stamp: float, frame_id: str = "track"):
    cls = ts.types[msgtype]
    time_cls = ts.types["builtin_interfaces/msg/Time"]
    header_cls = ts.types["std_msgs/msg/Header"]
    sec, nsec = divmod(int(round(stamp * 1e9)), 1_000_000_000)
    kw = {"header": header_cls(stamp=time_cls(sec=sec, nanosec=nsec), frame_id=frame_id)}
    for name in cls.__dataclass_fields__:
        if name in ("header", "__msgtype__"):
            continue
        if name in _LATER_FIELDS:  # older writers: integrity 0, no protection levels (inf;
            # ground truth's are 0)
            value = fields.get(name, 0.0 if name != "integrity" and
                               fields.get("source") == "truth" else _LATER_FIELDS[name])
        else:
            value = fields[name]
        if name == "covariance":
            value = np.asarray(value, dtype=np.float64).reshape(16)
        elif isinstance(value, (np.floating, np.integer, np.bool_)):
            value = value.item()
        kw[name] = value
    return cls(**kw)


def serialize(msgtype: str, fields: dict, stamp: float, frame_id: str = "track") -> bytes:
    fast = _serialize_fixed(msgtype, fields, stamp, frame_id)
    if fast is not None:
        return fast
    # our messages need only their own types (the same layout), not ROS 2's standard set
    ts = own_typestore() if msgtype in msg_texts() else typestore()
    return bytes(ts.serialize_cdr(_build(ts, msgtype, fields, stamp, frame_id), msgtype))


def _serialize_fixed(msgtype: str, fields: dict, stamp: float, frame_id: str) -> bytes | None:
    """:func:`serialize` of a message of a fixed layout (:func:`_fixed_fields`: the odometer,
    balise and command readings) with one ``struct`` pack: the same bytes as rosbags' CDR
    serialiser (``test_bag_decode``), a quarter of its time (it builds a message object
    first); None for any other layout."""
    frame = frame_id.encode() + b"\0"
    st = _fixed_struct(msgtype, len(frame))
    if st is None:
        return None
    st, names = st
    sec, nsec = divmod(int(round(stamp * 1e9)), 1_000_000_000)
    head = CDR_LE + _HEAD.pack(sec, nsec, len(frame)) + frame
    try:
        body = st.pack(*[fields[n] for n in names])
    except (KeyError, TypeError, struct.error):
        return None  # the general path, which says what is wrong with the fields
    # rosbags ends the message after its last field, without padding to the next alignment
    return head + body


# CDR sizes (= alignments) and struct codes of the primitive types a fixed layout may hold
_PRIMITIVES = {"float64": "d", "float32": "f", "int64": "q", "uint64": "Q", "int32": "i",
               "uint32": "I", "int16": "h", "uint16": "H", "int8": "b", "uint8": "B",
               "byte": "B", "char": "B", "bool": "?"}
CDR_LE = b"\x00\x01\x00\x00"  # the encapsulation header of little-endian plain CDR
_HEAD = struct.Struct("<iII")  # after it, the Header: stamp sec, nanosec, frame_id's length


@cache
def _fixed_fields(msgtype: str) -> tuple | None:
    """((name, struct code), ...) of a docs/interfaces.md message whose fields after its
    Header are all primitive scalars, in order; None for any other (strings, arrays)."""
    text = msg_texts().get(msgtype)
    if text is None:
        return None
    fields = []
    for line in text.splitlines():
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if len(words) != 2 or "=" in line.split("#", 1)[0]:
            return None  # a constant or a default value: not laid out here
        typ, name = words
        if not fields and typ in ("std_msgs/Header", "Header") and name == "header":
            fields.append(("header", ""))
            continue
        if typ not in _PRIMITIVES or not fields:
            return None
        fields.append((name, _PRIMITIVES[typ]))
    return tuple(fields[1:]) if fields and fields[0][0] == "header" else None


@cache
def _fixed_struct(msgtype: str, frame_len: int):
    """The struct of the fields after a Header whose frame_id takes ``frame_len`` bytes (its
    NUL included), or None (:func:`_fixed_fields`). CDR aligns each primitive to its size,
    counted from the end of the 4-byte encapsulation header."""
    fields = _fixed_fields(msgtype)
    if fields is None:
        return None
    at = 12 + frame_len  # sec, nanosec, the string's length, its bytes
    fmt = "<"
    for _, code in fields:
        size = struct.calcsize("<" + code)
        pad = -at % size
        fmt += "x" * pad + code
        at += pad + size
    return struct.Struct(fmt), tuple(n for n, _ in fields)


def _deserialize_fixed(msgtype: str, data: bytes):
    """:func:`deserialize` of a little-endian CDR message of a fixed layout read with one
    ``struct`` unpack (a tenth of the time of a decoded message object), or None where the
    layout is not such or the bytes do not fit it exactly (then the general decoder reads it)."""
    if data[:4] != CDR_LE or len(data) < 16:
        return None
    sec, nsec, frame_len = _HEAD.unpack_from(data, 4)
    st = _fixed_struct(msgtype, frame_len)
    if st is None:
        return None
    st, names = st
    body = 16 + frame_len
    size = st.size
    # the serialised message ends after its last field, padded to at most 3 bytes more
    if not size <= len(data) - body <= size + 3 or (frame_len and data[body - 1] != 0):
        return None
    return sec + nsec * 1e-9, dict(zip(names, st.unpack_from(data, body)))


def deserialize(msgtype: str, data: bytes) -> tuple[float, dict]:
    """(stamp in s, fields dict without the header) of a CDR message."""
    fast = _deserialize_fixed(msgtype, data)
    if fast is not None:
        return fast
    msg = own_typestore().deserialize_cdr(data, msgtype)
    fields = {k: getattr(msg, k) for k in msg.__dataclass_fields__
              if k not in ("header", "__msgtype__")}
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    return stamp, fields


class BagWriter:
    """A rosbag2 bag with MCAP storage; topics are created on first use. Readable as it is on
    disk from the start and after every :meth:`flush` (see the module's docstring)."""

    def __init__(self, path: str | os.PathLike, namespace: str = "/train"):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path} exists already: choose a new bag directory")
        self.namespace = namespace.rstrip("/")
        self.writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections: dict[str, object] = {}
        self.counts: dict[str, int] = {}
        self._tail_at: int | None = None  # file offset of the provisional tail, if written
        self.flush()

    def full_topic(self, topic: str) -> str:
        return topic if topic.startswith("/") else f"{self.namespace}/{topic}"

    def connection(self, topic: str, msgtype: str):
        name = self.full_topic(topic)
        conn = self.connections.get(name)
        if conn is None:
            if msgtype in msg_texts():
                conn = self.writer.add_connection(name, msgtype, msgdef=msgdef(msgtype),
                                                  rihs01=own_typestore().hash_rihs01(msgtype))
            else:
                conn = self.writer.add_connection(name, msgtype, typestore=typestore())
            self.connections[name] = conn
            self.counts[name] = 0
        return conn

    def write_raw(self, topic: str, msgtype: str, t_ns: int, data: bytes) -> None:
        self.writer.write(self.connection(topic, msgtype), int(t_ns), data)
        self.counts[self.full_topic(topic)] += 1

    def write(self, topic: str, stamp: float, fields: dict, t_ns: int | None = None,
              msgtype: str | None = None) -> None:
        msgtype = msgtype or TOPIC_TYPES[topic.split(f"{self.namespace}/")[-1].lstrip("/")]
        t_ns = int(round(stamp * 1e9)) if t_ns is None else t_ns
        self.write_raw(topic, msgtype, t_ns, serialize(msgtype, fields, stamp))

    def flush(self) -> None:
        """Close the pending MCAP chunk, end the file with a provisional footer, write
        metadata.yaml for what is on disk, and sync both.

        After a flush, everything written so far survives a crash or ``kill -9`` in a bag that
        rosbags' AnyReader and :func:`read_bag` open as it is; only the summary (the index) is
        missing. The next chunk overwrites the provisional tail. (rosbags closes a chunk only at
        1 MiB and writes metadata.yaml only at close; this reaches into its writer to do both
        sooner.)
        """
        storage = getattr(self.writer, "storage", None)
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and chunk.bio.tell():
            storage.close_chunk()
        bio = getattr(storage, "bio", None)
        if bio is None:
            return
        at = bio.tell()
        bio.write(PROVISIONAL_TAIL)
        bio.flush()
        os.fsync(bio.fileno())
        bio.seek(at)  # the next chunk (or the summary at close) replaces the tail
        self._tail_at = at
        self._write_metadata(storage.path.name)

    def _write_metadata(self, filename: str) -> None:
        """metadata.yaml as rosbags' Writer.close writes it, for the messages flushed so far."""
        import yaml
        from rosbags.rosbag2.metadata import dump_qos_v9

        w = self.writer
        count = sum(w.counts.values())
        start = w.min_timestamp if count else 0
        duration = max(0, w.max_timestamp - w.min_timestamp) if count else 0
        info = {
            "version": w.version,
            "storage_identifier": "mcap",
            "relative_file_paths": [filename],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": c.topic, "type": c.msgtype,
                                    "serialization_format": c.ext.serialization_format,
                                    "offered_qos_profiles": dump_qos_v9(
                                        c.ext.offered_qos_profiles),
                                    "type_description_hash": c.digest},
                 "message_count": w.counts[c.id]}
                for c in w.connections],
            "compression_format": "",
            "compression_mode": "",
            "files": [{"path": filename, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": count}],
            "custom_data": None,
            "ros_distro": "rosbags",
        }
        # replaced atomically; not synced: a killed process leaves the page cache to the kernel,
        # and a second sync per flush would stall the recorder on a busy disk
        tmp = self.path / "metadata.yaml.tmp"
        tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
        tmp.replace(self.path / "metadata.yaml")

    def close(self) -> None:
        if self.writer is not None:
            bio = getattr(getattr(self.writer, "storage", None), "bio", None)
            if bio is not None and self._tail_at is not None and bio.tell() == self._tail_at:
                bio.truncate()  # the summary replaces the provisional tail
            self.writer.close()
            self.writer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclass
class Bag:
    """A bag read into memory: per topic (relative name), a list of (t_ns, stamp_s, fields)."""

    path: Path
    namespace: str
    topics: dict[str, list[tuple[int, float, dict]]] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)  # topic -> why it was not read

    def series(self, topic: str, key: str) -> np.ndarray:
        return np.array([f[key] for _, _, f in self.topics.get(topic, [])], dtype=float)

    def stamps(self, topic: str) -> np.ndarray:
        return np.array([s for _, s, _ in self.topics.get(topic, [])], dtype=float)

    def recv_times(self, topic: str) -> np.ndarray:
        return np.array([t for t, _, _ in self.topics.get(topic, [])], dtype=float) * 1e-9


def read_bag(path: str | os.PathLike, namespace: str | None = None,
             topics: tuple[str, ...] | None = None) -> Bag:
    """Read every docs/interfaces.md topic of a rosbag2/MCAP bag (a directory or a .mcap file), or
    only ``topics`` (relative names): the others' messages are then never decoded.

    Works on bags written by rosbags, by rosbag2 and by the ``mcap`` writer with ROS 2 schemas.
    Topics of other types are listed in ``Bag.skipped`` with the reason.
    """
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag")
    if p.is_dir() and (not (p / "metadata.yaml").exists()
                       or not all(_is_closed(f) for f in p.glob("*.mcap"))):
        return _recover(p, namespace, topics)
    plain = _read_plain(p, namespace, topics)
    if plain is not None:
        return plain
    from rosbags.highlevel import AnyReader

    paths = [p]
    try:
        reader = AnyReader(paths, default_typestore=own_typestore())
        reader.open()
    except Exception as exc:
        raise BagError(f"{p}: unreadable bag ({type(exc).__name__}: {exc})") from None
    try:
        conns = list(reader.connections)
        if namespace is None:
            namespace = _guess_namespace([(c.topic, c.msgtype) for c in conns])
        bag = Bag(path=p, namespace=namespace)
        usable = []
        for c in conns:
            rel = c.topic[len(namespace) + 1:] if c.topic.startswith(namespace + "/") else c.topic
            if c.msgtype not in msg_texts() and c.msgtype != "rosgraph_msgs/msg/Clock":
                bag.skipped[c.topic] = f"type {c.msgtype} is not a docs/interfaces.md type"
                continue
            if c.msgtype == "rosgraph_msgs/msg/Clock" or (topics is not None
                                                           and rel not in topics):
                continue
            bag.types[rel] = c.msgtype
            bag.topics.setdefault(rel, [])
            usable.append((c, rel))
        rel_of = {c.id: rel for c, rel in usable}
        for conn, t_ns, raw in reader.messages(connections=[c for c, _ in usable]):
            try:
                stamp, fields = deserialize(conn.msgtype, raw)
            except Exception as exc:
                try:  # a bag written with an older definition (TrainState before integrity)
                    stamp, fields = _deserialize_own(reader, conn.msgtype, raw)
                except Exception:
                    bag.skipped.setdefault(conn.topic, f"undecodable message ({exc})")
                    continue
            bag.topics[rel_of[conn.id]].append((t_ns, stamp, fields))
    except BagError:
        raise
    except Exception as exc:
        raise BagError(f"{p}: unreadable bag ({type(exc).__name__}: {exc})") from None
    finally:
        reader.close()
    return bag


def _read_plain(p: Path, namespace: str | None, topics: tuple[str, ...] | None) -> Bag | None:
    """:func:`read_bag` from a closed bag of one MCAP file with uncompressed
    chunks (what the generator, the recorder and csv2bag write), its records walked here with
    ``struct`` and its messages decoded by :func:`deserialize`; None for anything else (then
    rosbags reads it). The same Bag as rosbags' reader gives, each topic in log-time order (ties
    in file order), without rosbags' import and per-message objects: a third of the time."""
    files = [p] if p.is_file() else sorted(p.glob("*.mcap"))
    if len(files) != 1:
        return None
    try:
        data = files[0].read_bytes()
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}  # id -> (topic, message type)
        raw: dict[int, list] = {}  # channel id -> [(log time, data)]
        head, msg_head = struct.Struct("<BQ"), struct.Struct("<HIQQ")

        def text(buf, at):
            n = int.from_bytes(buf[at:at + 4], "little")
            return bytes(buf[at + 4:at + 4 + n]).decode(), at + 4 + n

        def walk(buf, at, end):
            while at < end:
                op, n = head.unpack_from(buf, at)
                at += 9
                if op == 0x05:  # Message
                    cid, _, t_ns, _ = msg_head.unpack_from(buf, at)
                    lst = raw.get(cid)
                    if lst is None:
                        lst = raw[cid] = []
                    lst.append((t_ns, bytes(buf[at + 22:at + n])))
                elif op == 0x06:  # Chunk
                    comp, c = text(buf, at + 28)
                    size = int.from_bytes(buf[c:c + 8], "little")
                    if comp:
                        raise ValueError("compressed chunk")
                    walk(buf, c + 8, c + 8 + size)
                elif op == 0x03:  # Schema
                    sid = int.from_bytes(buf[at:at + 2], "little")
                    name, c = text(buf, at + 2)
                    enc, _ = text(buf, c)
                    if enc != "ros2msg":
                        raise ValueError(f"schema encoding {enc}")
                    schemas[sid] = name
                elif op == 0x04:  # Channel
                    cid, sid = struct.unpack_from("<HH", buf, at)
                    topic, c = text(buf, at + 4)
                    enc, _ = text(buf, c)
                    if enc != "cdr":
                        raise ValueError(f"message encoding {enc}")
                    channels[cid] = (topic, schemas[sid])
                elif op in (0x0F, 0x02):  # Data End, Footer: the summary follows
                    return
                at += n

        if data[:8] != MAGIC:
            return None
        walk(memoryview(data), 8, len(data))
    except (ValueError, KeyError, IndexError, struct.error, OSError, UnicodeDecodeError):
        return None
    if set(raw) - set(channels):
        return None  # a message on a channel never declared: rosbags says what is wrong
    if namespace is None:
        namespace = _guess_namespace(list(channels.values()))
    bag = Bag(path=p, namespace=namespace)
    for cid in sorted(channels):  # rosbags lists connections in channel order
        topic, msgtype = channels[cid]
        rel = topic[len(namespace) + 1:] if topic.startswith(namespace + "/") else topic
        if msgtype not in msg_texts() and msgtype != "rosgraph_msgs/msg/Clock":
            bag.skipped[topic] = f"type {msgtype} is not a docs/interfaces.md type"
            continue
        if msgtype == "rosgraph_msgs/msg/Clock" or (topics is not None and rel not in topics):
            continue
        bag.types[rel] = msgtype
        msgs = bag.topics.setdefault(rel, [])
        for t_ns, buf in sorted(raw.get(cid, []), key=lambda m: m[0]):
            try:
                stamp, fields = deserialize(msgtype, buf)
            except Exception:  # an older definition: the bag's own, through rosbags
                return None
            msgs.append((t_ns, stamp, fields))
    return bag


def _deserialize_own(reader, msgtype: str, raw: bytes) -> tuple[float, dict]:
    """(stamp, fields) with the definition the bag itself carries (AnyReader's typestore)."""
    msg = reader.deserialize(raw, msgtype)
    fields = {k: getattr(msg, k) for k in msg.__dataclass_fields__
              if k not in ("header", "__msgtype__")}
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, fields


def _is_closed(mcap: Path) -> bool:
    """An MCAP file its writer closed: it ends in a footer that points to a summary (a file
    whose writer died ends in a provisional footer without one, or in a cut record)."""
    try:
        with open(mcap, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell() < 8 + 37:
                return False
            fh.seek(-37, os.SEEK_END)
            tail = fh.read(37)
    except OSError:
        return False
    return (tail[-8:] == MAGIC and tail[0] == 0x02
            and int.from_bytes(tail[9:17], "little") != 0)


def _guess_namespace(topics: list[tuple[str, str]]) -> str:
    """The namespace of a bag's contract topics, from its (topic, message type) pairs: the
    prefix under which the most topics carry their contract type (``odometer`` an
    OdometerReading, ...). A topic of another type that ends in a contract name (a vehicle's
    own ``/vehicle/odometer`` as std_msgs/String) says nothing about it: taken first, it made
    every input look missing."""
    for typed in (True, False):  # by name alone where no topic has its type (then refused
        votes: dict = {}         # by type, with the reason, rather than looked for elsewhere)
        for t, msgtype in topics:
            for rel, want in TOPIC_TYPES.items():
                if t.endswith("/" + rel) and (msgtype == want or not typed):
                    ns = t[: -len(rel) - 1]
                    votes[ns] = votes.get(ns, 0) + 1
        if votes:
            return max(votes, key=lambda ns: (votes[ns], -len(ns)))
    return ""


def _complete_messages(files) -> tuple[list, str]:
    """Every complete message of MCAP files whose writer may have died, in file order:
    [(log_time ns, topic, schema name, schema text, data)], and the reason the read stopped
    early ("" if it did not). The first truncated or corrupt record ends a file's read."""
    from mcap.stream_reader import StreamReader

    schemas: dict[int, tuple[str, str]] = {}
    channels: dict[int, tuple[str, str, str]] = {}
    out: list = []
    truncated = ""
    for f in files:
        with open(f, "rb") as fh:
            try:
                for rec in StreamReader(fh).records:
                    kind = type(rec).__name__
                    if kind == "Schema":
                        schemas[rec.id] = (rec.name, bytes(rec.data).decode(errors="replace"))
                    elif kind == "Channel":
                        name, text = schemas.get(rec.schema_id, ("", ""))
                        channels[rec.id] = (rec.topic, name, text)
                    elif kind == "Message" and rec.channel_id in channels:
                        topic, msgtype, text = channels[rec.channel_id]
                        out.append((rec.log_time, topic, msgtype, text, bytes(rec.data)))
            except Exception as exc:  # a truncated tail: keep what was complete
                truncated = f"{type(exc).__name__}"
    return out, truncated


def _recover(p: Path, namespace: str | None, topics: tuple[str, ...] | None = None) -> Bag:
    """Read a bag whose writer died (no metadata.yaml, no MCAP summary): every complete chunk.

    The MCAP records are streamed in file order; the first truncated or corrupt record ends the
    read, and everything before it is kept.
    """

    files = sorted(p.glob("*.mcap"))
    if not files:
        raise BagError(f"{p}: no metadata.yaml and no .mcap file: not a rosbag2/MCAP bag")
    msgs, truncated = _complete_messages(files)
    if namespace is None:
        namespace = _guess_namespace(sorted({(m[1], m[2]) for m in msgs}))
    bag = Bag(path=p, namespace=namespace)
    if not truncated and all(_is_closed(f) for f in files):
        # only metadata.yaml is missing (copied without it): every file is complete
        bag.skipped["(file tail)"] = (f"no metadata.yaml; the .mcap files are complete and "
                                      f"were read as they are ('python -m train_core.bagio "
                                      f"repair {p}' writes it)")
    else:
        bag.skipped["(file tail)"] = (f"bag was not closed; read up to the last complete "
                                      f"record{f' ({truncated})' if truncated else ''}; "
                                      f"'python -m train_core.bagio repair {p}' indexes it")
    for t_ns, topic, msgtype, _, data in sorted(msgs, key=lambda r: r[0]):
        rel = topic[len(namespace) + 1:] if topic.startswith(namespace + "/") else topic
        if msgtype not in msg_texts():
            bag.skipped[topic] = f"type {msgtype} is not a docs/interfaces.md type"
            continue
        if topics is not None and rel not in topics:
            continue
        stamp, fields = deserialize(msgtype, data)
        bag.types[rel] = msgtype
        bag.topics.setdefault(rel, []).append((t_ns, stamp, fields))
    return bag


def repair_bag(path: str | os.PathLike, keep_broken: bool = True) -> Path:
    """Make a bag whose writer died (``kill -9``: no MCAP summary, perhaps no footer or no
    metadata.yaml) a normal, indexed bag again, for every reader and ``ros2 bag``.

    Every complete record is copied, in log-time order, into a new bag written by rosbags
    (summary, end magic, metadata.yaml); the original directory is kept beside it as
    ``<bag>.broken`` (``keep_broken=False`` deletes it). Returns the repaired bag's path.
    Raises BagError if the bag is not a broken rosbag2/MCAP bag.
    """
    import shutil
    import tempfile


    p = Path(path)
    if not p.is_dir():
        raise BagError(f"{p}: not a bag directory")
    files = sorted(p.glob("*.mcap"))
    if not files:
        raise BagError(f"{p}: no .mcap file: not a rosbag2/MCAP bag")
    if (p / "metadata.yaml").exists() and all(_is_closed(f) for f in files):
        raise BagError(f"{p}: was closed by its writer: nothing to repair")
    # the truncated tail ends the copy; what was complete is kept
    raw = [(t_ns, i, topic, msgtype, text, data)
           for i, (t_ns, topic, msgtype, text, data) in enumerate(_complete_messages(files)[0])]
    tmp = Path(tempfile.mkdtemp(prefix=".repair-", dir=p.parent))
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer

        out = tmp / p.name
        writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        conns: dict[str, object] = {}
        try:
            for t_ns, _, topic, msgtype, text, data in sorted(raw, key=lambda r: r[:2]):
                conn = conns.get(topic)
                if conn is None:
                    if msgtype in msg_texts():
                        conn = writer.add_connection(topic, msgtype, msgdef=msgdef(msgtype),
                                                     rihs01=typestore().hash_rihs01(msgtype))
                    else:  # another package's type: its embedded definition, as recorded
                        conn = writer.add_connection(topic, msgtype, msgdef=text, rihs01="")
                    conns[topic] = conn
                writer.write(conn, t_ns, data)
        finally:
            writer.close()
        broken = p.with_name(p.name + ".broken")
        if broken.exists():
            raise BagError(f"{broken} exists: move it away first")
        p.rename(broken)
        out.rename(p)
        if not keep_broken:
            shutil.rmtree(broken)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return p


def main(argv=None) -> int:
    """``python -m train_core.bagio repair BAG``: see :func:`repair_bag`."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="python -m train_core.bagio",
                                 description="Repair a bag whose recorder was killed.")
    ap.add_argument("command", choices=["repair"])
    ap.add_argument("bag", help="bag directory whose writer did not close it")
    ap.add_argument("--delete-broken", action="store_true",
                    help="delete the original instead of keeping it as BAG.broken")
    args = ap.parse_args(argv)
    try:
        before = read_bag(args.bag)
        p = repair_bag(args.bag, keep_broken=not args.delete_broken)
    except (BagError, OSError) as exc:
        print(f"repair: {exc}", file=sys.stderr)
        return 2
    n = sum(len(v) for v in before.topics.values())
    print(f"repaired {p}: {n} messages on {len(before.topics)} topics"
          + ("" if args.delete_broken else f"; original kept as {p}.broken"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
