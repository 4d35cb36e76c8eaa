"""rosbag2 recordings (sqlite3 and mcap storage) in and out, with rosbags.

``read_recording`` opens a bag with ``AnyReader`` (the bag's embedded definitions, or our
Jazzy typestore for bags without them), picks the radar, NavSatFix and Odometry topics
(``select_topics``), decodes every message with ``io.messages`` and feeds a
``RecordingBuilder``: the same path the node takes message by message. Stamps are header
stamps, never the bag's receive times.

Every failure of the input (missing path, not a bag, corrupt metadata or storage, a topic
that is not there, a message we cannot decode) becomes one ``BagReadError`` or
``DecodeError`` line naming the problem, with rosbags' error chained (``from err``).
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
import sqlite3
import struct
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import TypesysError

from radar_calib_ros.errors import BagReadError, DecodeError
from radar_calib_ros.io import messages as msgs
from radar_calib_ros.recording import Recording, RecordingBuilder

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.typesys.store import Typestore

    from radar_calib_ros.config import CalibConfig

__all__ = ['RADAR_TYPES', 'ROLE_TYPES', 'BagPaths', 'bag_label', 'configured_radar_frame_id',
           'radar_frame_ids', 'radar_topics', 'read_recording', 'select_topics', 'write_bag']

#: Message types accepted per role.
RADAR_TYPES = (msgs.POINTCLOUD2, msgs.RADARSCAN)
ROLE_TYPES: dict[str, tuple[str, ...]] = {
    'radar': RADAR_TYPES, 'navsat': (msgs.NAVSATFIX,), 'odom': (msgs.ODOMETRY,)}
_ROLE_PARAMETER = {'radar': 'radar_topic', 'navsat': 'navsat_topic', 'odom': 'odom_topic'}
#: The two vehicle-pose roles: either alone gives a pose (NavSatFix with the course over
#: ground, Odometry with vehicle.odom_is_utm), so a named one that is absent is dropped,
#: with a warning, while the other is there.
_POSE_ROLES = ('navsat', 'odom')
_LOG = logging.getLogger(__name__)

#: What a rosbag2 storage file is called (mcap and sqlite3 storage).
_STORAGE_SUFFIXES = ('.mcap', '.db3')

# What a damaged storage file raises inside rosbags' readers besides its own errors: sqlite3
# for a damaged database, struct/EOF/Value errors from the mcap record parser.
_STORAGE_ERRORS = (ReaderError, AnyReaderError, SerdeError, sqlite3.DatabaseError,
                   struct.error, EOFError, ValueError, KeyError, IndexError, UnicodeError)
_PROGRESS_EVERY = 1000
#: One rosbag2 directory, or several read as one recording (``_ChainReader``).
BagPaths = str | Path | Sequence[str | Path]


# --- topics ------------------------------------------------------------------------------

def _listing(topics: Mapping[str, str]) -> str:
    return ', '.join(f'{t} ({msgtype})' for t, msgtype in sorted(topics.items())) or 'none'


def _same_topic(a: str, b: str) -> bool:
    return a.lstrip('/') == b.lstrip('/')


def select_topics(topics: Mapping[str, str], config: CalibConfig) -> dict[str, str | None]:
    """The bag topic of each role: ``'radar'``, ``'navsat'`` and ``'odom'``.

    A topic parameter (``radar_topic``, ...) matches with or without its leading '/'. When
    the parameter was not set explicitly (``config.explicit``) and its default name is not
    in the bag, the topic is picked by message type. An explicitly empty parameter turns
    that role off (None). A named vehicle-pose topic (NavSatFix or Odometry) that is not
    in the bag is dropped with a warning when the other one is there (a parameters file
    written for both, a recording with one).

    Parameters
    ----------
    topics : mapping of str to str
        Topic name -> message type, of the bag.
    config : CalibConfig

    Returns
    -------
    dict of str to str or None
        The chosen topic per role; None when the bag has none (radar never).

    Raises
    ------
    BagReadError
        A requested topic is not in the bag (the message lists those there; for a pose topic
        only when the other pose topic is missing too) or has the wrong type; several topics
        of a role's type and no parameter naming one (they are listed); no radar topic at
        all.
    """
    chosen: dict[str, str | None] = {}
    absent: dict[str, str] = {}
    for role, parameter in _ROLE_PARAMETER.items():
        wanted: str = getattr(config, parameter)
        explicit = parameter in config.explicit
        accepted = ROLE_TYPES[role]
        type_names = ' or '.join(accepted)
        if explicit and not wanted:
            chosen[role] = None
            continue
        named = [t for t in topics if _same_topic(t, wanted)]
        if named and topics[named[0]] in accepted:
            chosen[role] = named[0]
            continue
        if explicit:
            if named:
                raise BagReadError(f'{parameter} {wanted!r} has type {topics[named[0]]}, '
                                   f'expected {type_names}')
            missing = (f'{parameter} {wanted!r} is not in the bag; topics there: '
                       f'{_listing(topics)}')
            if role not in _POSE_ROLES:
                raise BagReadError(missing)
            absent[role] = missing
            chosen[role] = None
            continue
        candidates = sorted(t for t, msgtype in topics.items() if msgtype in accepted)
        if len(candidates) > 1:
            raise BagReadError(f'several {type_names} topics and no {parameter} naming one: '
                               f'{", ".join(candidates)}; set {parameter}')
        chosen[role] = candidates[0] if candidates else None
    if chosen['radar'] is None:
        raise BagReadError(f'no radar topic ({" or ".join(RADAR_TYPES)}) in the bag; topics '
                           f'there: {_listing(topics)}')
    if chosen['navsat'] is None and chosen['odom'] is None and not absent:
        # the wrong bag (the radar's own recording), not data that cannot be calibrated
        raise BagReadError(f'no vehicle pose topic ({" or ".join(ROLE_TYPES["navsat"])} or '
                           f'{" or ".join(ROLE_TYPES["odom"])}) in the bag; topics there: '
                           f'{_listing(topics)}')
    for role, missing in absent.items():
        other = _POSE_ROLES[1 - _POSE_ROLES.index(role)]
        if chosen[other] is None:
            raise BagReadError(missing)
        _LOG.warning('%s: the vehicle pose comes from %s %s alone', missing,
                     _ROLE_PARAMETER[other], chosen[other])
    return chosen


# --- reading -----------------------------------------------------------------------------

def _check_bag_path(path: Path) -> Path:
    """The bag directory to open (a path to its metadata.yaml means the directory)."""
    if path.name == 'metadata.yaml' and path.is_file():
        path = path.parent
    if not path.exists():
        raise BagReadError(f'bag {str(path)!r} does not exist')
    if path.is_dir() and not (path / 'metadata.yaml').is_file():
        # A recording cut short (the recorder killed, the laptop's battery) leaves its
        # storage file without the metadata.yaml written at the end; one such file reads
        # on its own (a thirteenth probe's were refused although intact), several (a split
        # recording) one by one (``_SplitReader``).
        files = _storage_files(path)
        if len(files) == 1:
            _LOG.warning('%r has no metadata.yaml (a recording interrupted before it was '
                         'written?): reading its storage file %s alone', str(path),
                         files[0].name)
            return files[0]
        if not files:
            packed = sorted(p.name for p in path.iterdir()
                            if p.suffix == '.zstd' and Path(p.stem).suffix in _STORAGE_SUFFIXES)
            if packed:
                # a recording with file compression whose metadata.yaml, which says so, is
                # lost (a fiftieth probe read 'no storage file' beside its .mcap.zstd)
                raise BagReadError(
                    f'{str(path)!r} has no metadata.yaml and its storage files are '
                    f'zstd-compressed ({", ".join(packed[:3])}'
                    f'{", ..." if len(packed) > 3 else ""}): restore the metadata.yaml, or '
                    'decompress them (zstd -d) and read the folder again')
            raise BagReadError(f'{str(path)!r} is not a rosbag2 bag (no metadata.yaml and no '
                               'storage file in it)')
    return path


class _BagReader(Protocol):
    """What the reading below needs of a bag reader (AnyReader or ``_PlainReader``)."""

    connections: list[Any]

    def messages(self, connections: Iterable[Any] = ...) -> Iterator[tuple[Any, int, Any]]:
        ...

    def deserialize(self, rawdata: bytes, msgtype: str) -> Any:
        ...

    def close(self) -> None:
        ...


@dataclasses.dataclass(frozen=True)
class _Topic:
    """One topic of a sqlite3 storage file, as rosbags' ``Connection`` names it."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


class _JazzyDecoding:
    """Decoding with our Jazzy typestore, for the readers that do not parse a bag's own
    message definitions (the topics we decode are standard ROS 2 types)."""

    def __init__(self) -> None:
        self._typestore = msgs.get_typestore()

    def deserialize(self, rawdata: bytes, msgtype: str) -> Any:
        return self._typestore.deserialize_cdr(rawdata, msgtype)


class _PlainReader(_JazzyDecoding):
    """A bag read without its embedded message definitions, decoded with our Jazzy
    typestore: rosbags' storage reader for mcap, sqlite3 itself (read-only) for sqlite3
    storage, so that a write-ahead log left by an interrupted recording is read too.

    AnyReader parses every topic's embedded definition when it opens a bag, so one vendor
    topic with a broken or incomplete definition made a twenty-fifth probe's whole
    recording unreadable (exit 2) although its radar, fix and odometry were intact; and it
    opens sqlite3 files as immutable, which skips a ``.db3-wal`` file (the probe's
    interrupted recording: 5 of its 9 passes read, nothing said). The topics we decode are
    standard ROS 2 types, which our typestore knows.
    """

    def __init__(self, path: Path) -> None:
        super().__init__()
        self._sqlite: list[tuple[sqlite3.Connection, dict[int, _Topic]]] = []
        self._rosbag: Any = None
        files = _storage_files(path)
        self.connections: list[Any] = []
        try:
            if files and all(f.suffix == '.db3' for f in files):
                for file in files:
                    self._open_sqlite(file)
            else:
                self._rosbag = Reader(path)
                self._rosbag.open()
                self.connections = list(self._rosbag.connections)
        except BaseException:
            self.close()
            raise

    def _open_sqlite(self, file: Path) -> None:
        db = sqlite3.connect(f'file:{file}?mode=ro', uri=True)
        topics: dict[int, _Topic] = {}
        self._sqlite.append((db, topics))
        rows = db.execute('SELECT topics.id, name, type, count(messages.id) FROM topics LEFT '
                          'JOIN messages ON messages.topic_id = topics.id GROUP BY topics.id')
        for topic_id, name, msgtype, count in rows.fetchall():
            topic = _Topic(int(topic_id), str(name), str(msgtype), int(count))
            topics[topic.id] = topic
            self.connections.append(topic)

    def messages(self, connections: Iterable[Any] = ()) -> Iterator[tuple[Any, int, bytes]]:
        wanted = list(connections)
        if self._rosbag is not None:
            yield from self._rosbag.messages(connections=wanted)
            return
        for db, topics in self._sqlite:
            ids = [t.id for t in wanted if topics.get(t.id) is t] if wanted else list(topics)
            if not ids:
                continue
            query = ('SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN '
                     f'({",".join("?" * len(ids))}) ORDER BY timestamp')
            for topic_id, stamp, data in db.execute(query, ids):
                yield topics[topic_id], int(stamp), data

    def close(self) -> None:
        for db, _ in self._sqlite:
            db.close()
        if self._rosbag is not None and self._rosbag.is_open:
            self._rosbag.close()


_MCAP_MAGIC = b'\x89MCAP0\r\n'


class _CutMcap(_JazzyDecoding):
    """An MCAP file cut short (no footer, no index: the recorder lost power or was
    killed): its whole records before the cut, scanned in file order (the order rosbag2
    wrote them in), through rosbags' own MCAP record scanner.

    A twenty-fifth probe's recording cut at 70 % was refused (exit 2, with `mcap recover`
    of the mcap CLI to repair it), although the two thirds of its messages before the cut
    calibrated to 8 cm; the data already written is the user's, and is read.
    """

    def __init__(self, file: Path) -> None:
        from rosbags.rosbag2.storage_mcap import McapReader
        super().__init__()
        self._reader = McapReader(file)
        bio = self._reader.bio = file.open('rb')
        try:
            size = file.stat().st_size
            if bio.read(8) != _MCAP_MAGIC or bio.read(1) != b'\x01':
                raise BagReadError(f'{str(file)!r} is not an MCAP file')
            (length,) = struct.unpack('<Q', bio.read(8))
            start = 17 + length
            end = _whole_records_end(bio, start, size)
            self.kept_fraction = (end - start) / max(size - start, 1)
            self._reader.data_start, self._reader.data_end = start, end
            self._reader.meta_scan()
        except BaseException:
            self._reader.close()
            raise
        statistics = self._reader.statistics
        counts = statistics.channel_message_counts if statistics is not None else {}
        self.connections: list[Any] = [c._replace(msgcount=counts.get(c.id, 0))
                                       for c in self._reader.connections]

    def messages(self, connections: Iterable[Any] = ()) -> Iterator[tuple[Any, int, Any]]:
        yield from self._reader.messages_scan(list(connections) or self.connections)

    def close(self) -> None:
        self._reader.close()


def _whole_records_end(bio: Any, start: int, size: int) -> int:
    """Offset after the last whole top-level MCAP record (opcode, length, body) from
    ``start`` in a file of ``size`` bytes."""
    pos = start
    while pos + 9 <= size:
        bio.seek(pos + 1)
        (length,) = struct.unpack('<Q', bio.read(8))
        if pos + 9 + length > size:
            break
        pos += 9 + length
    return pos


def _cut_mcap(path: Path) -> _CutMcap | None:
    """The reader of a bag that is one MCAP file cut short, or None where it is not one
    or cannot be read so."""
    files = _storage_files(path)
    if len(files) != 1 or files[0].suffix != '.mcap':
        return None
    try:
        cut = _CutMcap(files[0])
    except (OSError, BagReadError, *_STORAGE_ERRORS) as err:
        _LOG.debug('reading %s up to its cut failed: %s', files[0], err)
        return None
    if not any(c.msgcount for c in cut.connections):
        cut.close()    # cut inside its first chunk: nothing to read, the repair to name
        return None
    _LOG.warning('%r was cut short (the recording interrupted): read up to the cut, the %d '
                 'messages of its whole chunks (%.0f %% of the file)', str(path),
                 sum(c.msgcount for c in cut.connections), 100 * cut.kept_fraction)
    return cut


def _storage_files(path: Path) -> list[Path]:
    """The storage files of a bag (a directory) or the one file given, in the order
    rosbag2 wrote them (``name_2`` before ``name_10``)."""
    if path.is_file():
        return [path]
    return sorted((p for p in path.iterdir() if p.suffix in _STORAGE_SUFFIXES),
                  key=_split_order)


def _split_order(file: Path) -> tuple[str, int, str]:
    stem, _, index = file.stem.rpartition('_')
    return (stem, int(index), file.suffix) if index.isdigit() else (file.stem, -1, file.suffix)


class _PartsReader:
    """Readers read one after the other as one: their connections together, each message
    read and decoded by the reader that holds it (a bag's AnyReader with its embedded
    definitions: ``_messages`` deserialises each message as it is yielded)."""

    def __init__(self, parts: list[Any]) -> None:
        self._parts = parts
        self.connections: list[Any] = [c for part in parts for c in part.connections]
        self._owner = {id(c): part for part in parts for c in part.connections}
        self._current: Any = parts[0]

    def messages(self, connections: Iterable[Any] = ()) -> Iterator[tuple[Any, int, Any]]:
        wanted = list(connections) or self.connections
        for part in self._parts:
            own = [c for c in wanted if self._owner.get(id(c)) is part]
            if own:
                self._current = part
                yield from part.messages(own)

    def deserialize(self, rawdata: bytes, msgtype: str) -> Any:
        return self._current.deserialize(rawdata, msgtype)

    def close(self) -> None:
        for part in self._parts:
            part.close()


class _SplitReader(_PartsReader):
    """A split recording without its metadata.yaml (rosbag2 writes it when the recording
    ends: a recorder that lost power leaves ``name_0.mcap``, ``name_1.mcap``, ... and the
    last one cut short). Each storage file is read on its own (``_PlainReader``; one cut
    short, ``_CutMcap``), in the order they were written; a file without a single whole
    message is left out with a warning. `ros2 bag reindex` was the advice before, which
    needs ROS and cannot read the cut file either: the data already written is the
    user's."""

    def __init__(self, path: Path, damaged: str | None = None) -> None:
        parts: list[Any] = []
        files = _storage_files(path)
        if damaged is None:
            _LOG.warning('%r has no metadata.yaml (a split recording interrupted before it '
                         'was written?): reading its %d storage files one by one', str(path),
                         len(files))
        else:
            # A recorder killed mid-file, or a file lost in copying, made the whole split
            # recording unreadable through its metadata.yaml (a fiftieth probe's 11 whole
            # files of 12 refused for the last one cut short): the files are read as
            # without it, the damaged ones left out and named.
            _LOG.warning('%r cannot be read as its metadata.yaml describes it (%s): reading '
                         'its %d storage files one by one', str(path), damaged, len(files))
        try:
            for file in files:
                part = self._open_part(file)
                if part is not None:
                    parts.append(part)
        except BaseException:
            for part in parts:
                part.close()
            raise
        if not parts:
            raise BagReadError(f'{str(path)!r} has no metadata.yaml and none of its '
                               f'{len(files)} storage files holds a whole message')
        super().__init__(parts)

    @staticmethod
    def _open_part(file: Path) -> Any:
        try:
            return _PlainReader(file)
        except (OSError, *_STORAGE_ERRORS) as err:
            if 'malformed' in _reason(err).lower() or 'not a database' in _reason(err).lower():
                # a sqlite3 file cut short: its pages are not readable on their own
                _LOG.warning('%s cannot be read (%s; cut short?): left out', file.name,
                             _reason(err))
                return None
            if 'end magic' not in _reason(err).lower():
                raise BagReadError(f'reading {str(file)!r}: {_reason(err)}') from err
        cut = _cut_mcap(file)
        if cut is None:
            _LOG.warning('%s was cut short before its first whole message: left out',
                         file.name)
        return cut


class _ChainReader(_PartsReader):
    """Several bags of one recording read as one (``calibrate A B``): a recorder restarted
    in the middle of the drive, or the radar recorded at the roadside and the vehicle's
    poses in the vehicle. Each is opened as alone (``_open_reader``), in the order given;
    the ``RecordingBuilder`` orders the messages by their stamps, and drops a radar scan
    that two of them both hold (``radar_messages_duplicate``).

    Why: a fiftieth probe's drive, split by a recorder restart into two bags of 4-5 passes
    each, could only be calibrated whole by copying both storage files into one folder
    without metadata (9 passes, 2.7 cm, and a warning about an interrupted recording)."""

    def __init__(self, paths: list[Path], stack: ExitStack) -> None:
        parts = [stack.enter_context(_open_reader(path)) for path in paths]
        first: dict[str, tuple[str, Path]] = {}
        for path, part in zip(paths, parts):
            for connection in part.connections:
                msgtype, where = first.setdefault(connection.topic, (connection.msgtype, path))
                if msgtype != connection.msgtype:
                    raise BagReadError(
                        f'topic {connection.topic} is {msgtype} in {str(where)!r} and '
                        f'{connection.msgtype} in {str(path)!r}: bags read as one recording '
                        'must agree on their topics\' types')
        super().__init__(parts)

    def close(self) -> None:
        pass    # the parts close with the ExitStack that opened them


def _listed(path: BagPaths) -> list[str | Path]:
    """The bags ``path`` names, one or several."""
    return [path] if isinstance(path, (str, Path)) else list(path)


def _bag_paths(path: BagPaths) -> list[Path]:
    """The bag (or bags, read as one recording) that ``path`` names, a bag given twice
    refused (each message would count twice)."""
    paths = [Path(p) for p in _listed(path)]
    if not paths:
        raise BagReadError('no bag given')
    seen: dict[Path, Path] = {}
    for p in paths:
        key = _check_bag_path(p).resolve() if p.exists() else p.absolute()
        if key in seen:
            raise BagReadError(f'bag {str(p)!r} is given twice (as {str(seen[key])!r}): '
                               'give each bag of the recording once')
        seen[key] = p
    return paths


def bag_label(path: BagPaths) -> str:
    """The bag, or the bags read as one recording, in a message."""
    return ' + '.join(str(p) for p in _listed(path))


@contextmanager
def _open_bags(path: BagPaths) -> Iterator[tuple[_BagReader, Path]]:
    """A reader over the bag, or over several read as one (``_ChainReader``), with the path
    its errors name."""
    paths = _bag_paths(path)
    if len(paths) == 1:
        with _open_reader(paths[0]) as reader:
            yield reader, paths[0]
        return
    with ExitStack() as stack:
        yield _ChainReader(paths, stack), Path(bag_label(paths))


def _unread_logs(path: Path) -> list[Path]:
    """Write-ahead logs of sqlite3 storage files that still hold pages (a recording not
    closed cleanly), which an immutable open of the database does not see."""
    logs = [Path(f'{f}-wal') for f in _storage_files(path) if f.suffix == '.db3']
    return [w for w in logs if w.is_file() and w.stat().st_size > 0]


def _storage_opens(path: Path) -> bool:
    """Whether rosbags' storage reader, which parses no message definition, opens the bag:
    then what AnyReader failed on were the definitions."""
    try:
        with Reader(path):
            return True
    except (OSError, *_STORAGE_ERRORS):
        return False


@contextmanager
def _open_reader(path: Path) -> Iterator[_BagReader]:
    """A reader over one rosbag2 bag (AnyReader; ``_PlainReader`` where AnyReader cannot
    read the embedded definitions or would miss a write-ahead log; ``_CutMcap`` for one
    MCAP file cut short), its errors translated to BagReadError."""
    path = _check_bag_path(path)
    reader: Any = None
    try:
        logs = _unread_logs(path)
        if path.is_dir() and not (path / 'metadata.yaml').is_file():
            reader = _SplitReader(path)
        elif logs:
            _LOG.warning('%s holds messages not yet in its database (a recording not closed '
                         'cleanly): read through it, read-only', logs[0].name)
            reader = _PlainReader(path)
        else:
            reader = AnyReader([path], default_typestore=msgs.get_typestore())
            try:
                reader.open()
            except (AnyReaderError, KeyError, TypesysError) as err:
                if not _storage_opens(path):
                    raise
                _LOG.warning('the bag\'s embedded message definitions cannot be read (%s): '
                             'its topics are decoded with the standard ROS 2 Jazzy ones',
                             _reason(err))
                reader = _PlainReader(path)
    except PermissionError as err:
        raise BagReadError(f'reading bag {str(path)!r}: permission denied') from err
    except (OSError, *_STORAGE_ERRORS) as err:
        reason = _reason(err)
        cut = _cut_mcap(path) if 'end magic' in reason.lower() else None
        if cut is None and path.is_dir() and len(_storage_files(path)) > 1:
            try:
                cut = _SplitReader(path, damaged=reason)
            except (BagReadError, OSError, *_STORAGE_ERRORS):
                cut = None
        if cut is None:
            if 'end magic' in reason.lower():
                reason += (' (an MCAP file cut short: the recording was interrupted? `mcap '
                           'recover` of the mcap CLI rewrites what it holds into a readable '
                           'file)')
            raise BagReadError(f'reading bag {str(path)!r}: {reason}') from err
        reader = cut
    try:
        yield reader
    finally:
        try:
            reader.close()
        except (OSError, *_STORAGE_ERRORS):
            pass  # a close failure after a read failure must not hide the first error


def _reason(err: BaseException) -> str:
    """rosbags' message on one line (sqlite3 and YAML messages can span several)."""
    text = ' '.join(str(err).split()) or type(err).__name__
    return text if len(text) <= 300 else text[:297] + '...'


def radar_topics(path: BagPaths, velocity_field: str = '') -> list[str]:
    """Every radar topic (PointCloud2 or radar_msgs RadarScan) of a bag, sorted; of
    several, not the PointCloud2 topics without a radial velocity (``_not_radars``).

    Raises
    ------
    BagReadError
        The bag cannot be opened.
    """
    with _open_bags(path) as (reader, label):
        topics = {c.topic for c in reader.connections if c.msgtype in RADAR_TYPES}
        return sorted(topics - _not_radars(reader, label, velocity_field))


#: Messages of a PointCloud2 topic looked at for its fields (empty scans carry none).
_FIELD_PEEK_MESSAGES = 20


def _not_radars(reader: _BagReader, path: Path, velocity_field: str) -> set[str]:
    """Where a bag has several PointCloud2 / RadarScan topics: the PointCloud2 topics whose
    first cloud with fields has no radial-velocity field (a lidar beside the radar, as a
    simulator records it), which are not radars. Empty with one such topic, whose decoding
    then names what is missing."""
    candidates = [c for c in reader.connections if c.msgtype in RADAR_TYPES]
    if len({c.topic for c in candidates}) < 2:
        return set()
    out: set[str] = set()
    for connection in candidates:
        if connection.msgtype != msgs.POINTCLOUD2:
            continue
        for k, (_, _, msg) in enumerate(_messages(reader, [connection], path)):
            if list(msg.fields):
                if msgs.lacks_velocity_field(msg, velocity_field):
                    out.add(connection.topic)
                break
            if k + 1 >= _FIELD_PEEK_MESSAGES:
                break
    return out


def radar_frame_ids(path: BagPaths) -> dict[str, str]:
    """The header ``frame_id`` of the first message of every radar topic of a bag (of
    several, not the PointCloud2 topics without a radial velocity: ``_not_radars``).

    A topic without messages, or whose first message has an empty frame id, maps to ''.

    Raises
    ------
    BagReadError
        The bag cannot be opened or read.
    """
    frames: dict[str, str] = {}
    with _open_bags(path) as (reader, label):
        skip = _not_radars(reader, label, '')
        for connection in reader.connections:
            if (connection.msgtype not in RADAR_TYPES or connection.topic in frames
                    or connection.topic in skip):
                continue
            frames[connection.topic] = ''
            for _, _, msg in _messages(reader, [connection], label):
                frames[connection.topic] = str(msg.header.frame_id)
                break
    return dict(sorted(frames.items()))


def radar_fingerprints(path: BagPaths, topics: Iterable[str],
                       count: int = 8) -> dict[str, tuple[str, ...]]:
    """Topic -> digests of its first ``count`` serialised messages (empty for a topic with
    none): two topics with equal digests carry the same clouds.

    Raises
    ------
    BagReadError
        The bag cannot be opened or read.
    """
    wanted = set(topics)
    prints: dict[str, tuple[str, ...]] = {}
    with _open_bags(path) as (reader, label):
        for topic in sorted(wanted):
            connections = [c for c in reader.connections if c.topic == topic]
            digests: list[str] = []
            iterator = reader.messages(connections=connections) if connections else iter(())
            try:
                for _, _, rawdata in iterator:
                    digests.append(hashlib.sha1(bytes(rawdata)).hexdigest())
                    if len(digests) >= count:
                        break
            except (OSError, *_STORAGE_ERRORS) as err:
                raise BagReadError(f'reading bag {str(label)!r}: {_reason(err)}') from err
            prints[topic] = tuple(digests)
    return prints


def configured_radar_frame_id(path: BagPaths, config: CalibConfig) -> str:
    """The header ``frame_id`` of the radar topic the parameters pick (matched as
    :func:`select_topics` does, with or without the leading '/', else the bag's only radar
    topic); '' when none is picked or the header names none.

    Raises
    ------
    BagReadError
        The bag cannot be opened or read.
    """
    frames = radar_frame_ids(path)
    named = [t for t in frames if _same_topic(t, config.radar_topic)]
    if named:
        return frames[named[0]]
    return next(iter(frames.values())) if len(frames) == 1 else ''


def read_recording(path: BagPaths, config: CalibConfig, *,
                   progress: Callable[[int, int], None] | None = None,
                   radar_topic: str | None = None) -> Recording:
    """Read a rosbag2 recording into a :class:`Recording`.

    Parameters
    ----------
    path : str or Path, or a sequence of them
        A rosbag2 directory (sqlite3 or mcap storage), or several read as one recording.
    config : CalibConfig
        Topics, ``radar.velocity_field`` and what ``RecordingBuilder`` uses.
    progress : callable(done, total), optional
        Called every 1000 messages and at the end with the number of messages read
        and the total on the selected topics.
    radar_topic : str, optional
        Read this radar topic, as if ``radar_topic`` had been set explicitly (used to
        calibrate every radar of a bag in turn, see ``radar_topics``).

    Raises
    ------
    BagReadError
        Missing path, not a bag, corrupt metadata or storage, unknown or ambiguous topics.
    DecodeError
        No radar message of the topic could be decoded: the first one's problem (prefixed
        with its topic and stamp). Single malformed messages among good ones are skipped,
        counted (``radar_messages_malformed``) and named in the calibration's notes.
    InsufficientDataError
        No radar frame or no usable vehicle pose (from ``RecordingBuilder.build``).
    """
    if radar_topic is not None:
        config = dataclasses.replace(config, radar_topic=radar_topic,
                                     explicit=config.explicit | {'radar_topic'})
    builder = RecordingBuilder(config)
    with _open_bags(path) as (reader, label):
        topics = {c.topic: c.msgtype for c in reader.connections}
        if 'radar_topic' not in config.explicit:
            for topic in _not_radars(reader, label, config.radar.velocity_field):
                del topics[topic]
        chosen = select_topics(topics, config)
        roles = {topic: role for role, topic in chosen.items() if topic is not None}
        connections = [c for c in reader.connections if c.topic in roles]
        total = sum(c.msgcount for c in connections)
        velocity_field = config.radar.velocity_field
        done = 0
        first_error: DecodeError | None = None
        radar_frame: str | None = None
        other_radar: str | None = None
        for connection, received_ns, msg in _messages(reader, connections, label):
            if roles[connection.topic] == 'radar':
                frame_id = str(getattr(msg.header, 'frame_id', '') or '')
                keep = msgs.radar_frame_to_keep(frame_id, radar_frame, config)
                other = msgs.other_radar(frame_id, keep)
                if other:
                    builder.counters['radar_other_frame'] += 1
                    other_radar = other_radar or other
                    continue
                radar_frame = keep
            try:
                added = _add_message(builder, roles[connection.topic], connection, msg,
                                     velocity_field)
            except DecodeError as err:
                # One malformed cloud in a long drive (a driver's short write) costs one
                # frame, as in the node; a topic none of whose clouds decode is refused below
                builder.counters['radar_messages_malformed'] += 1
                first_error = first_error or err
            else:
                if added:
                    builder.note_receipt(roles[connection.topic],
                                         msgs.stamp_ns(msg.header), received_ns)
            done += 1
            if progress is not None and done % _PROGRESS_EVERY == 0:
                progress(done, total)
        if progress is not None:
            progress(done, total)
    if other_radar is not None:
        _LOG.warning('%s (%d clouds skipped)', other_radar,
                     builder.counters['radar_other_frame'])
    if first_error is not None:
        if builder.n_frames == 0:
            raise first_error
        _LOG.warning('%d radar messages could not be decoded and were skipped; the first: %s',
                     builder.counters['radar_messages_malformed'], first_error)
    return dataclasses.replace(builder.build(), sources={
        role: topic for role, topic in chosen.items() if topic is not None})


def _messages(reader: _BagReader, connections: list[Connection],
              path: Path) -> Iterator[tuple[Connection, int, Any]]:
    """(connection, record time [ns], message) of the given connections, deserialised,
    storage errors translated."""
    iterator = reader.messages(connections=connections)
    decompressed = False
    while True:
        try:
            item = next(iterator, None)
        except (OSError, *_STORAGE_ERRORS) as err:
            raise BagReadError(f'reading bag {str(path)!r}: {_reason(err)}') from err
        if item is None:
            return
        connection, bag_ns, rawdata = item
        plain = _plain(rawdata)
        if plain is not rawdata and not decompressed:
            decompressed = True
            _LOG.warning('the messages of %r are zstd-compressed though its metadata says '
                         'nothing of it (lost?): decompressed', str(path))
        try:
            msg = reader.deserialize(plain, connection.msgtype)
        except (AnyReaderError, SerdeError, *_STORAGE_ERRORS) as err:
            raise BagReadError(f'reading bag {str(path)!r}: a {connection.msgtype} message on '
                               f'{connection.topic} cannot be deserialised: {_reason(err)}'
                               ) from err
        yield connection, int(bag_ns), msg


#: The first bytes of a zstd frame.
_ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'


def _plain(rawdata: Any) -> Any:
    """A message's serialised bytes, decompressed where they are a zstd frame: a recording
    with message compression whose metadata.yaml (which says so) is lost hands them over
    compressed, and they read as 'unsupported CDR encapsulation' (a fiftieth probe)."""
    if bytes(rawdata[:4]) != _ZSTD_MAGIC:
        return rawdata
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        from backports import zstd  # type: ignore[import-not-found,no-redef]
    try:
        return zstd.decompress(bytes(rawdata))
    except zstd.ZstdError:
        return rawdata


def _add_message(builder: RecordingBuilder, role: str, connection: Connection, msg: Any,
                 velocity_field: str) -> bool:
    """Decode one message into the builder; False when it was dropped (counted): a pose
    the builder refuses, a radar scan without a header stamp (the node refuses it too: the
    contract times by header stamps, never by receipt). Only kept messages note their
    receipt, so that receipts and samples correspond one to one."""
    if role == 'radar':
        try:
            if connection.msgtype == msgs.RADARSCAN:
                frame = msgs.decode_radarscan(msg)
            else:
                frame = msgs.decode_pointcloud(msg, velocity_field)
        except DecodeError as err:
            raise DecodeError(f'{connection.topic} (stamp {msgs.stamp_ns(msg.header)} ns): '
                              f'{err}') from err
        if frame.stamp_ns <= 0:
            builder.counters['radar_stamps_unset'] += 1
            return False
        builder.add_radar_frame(frame)
        return True
    if role == 'navsat':
        return builder.add_fix(msgs.decode_navsatfix(msg))
    return builder.add_odometry(msgs.decode_odometry(msg))


# --- writing -----------------------------------------------------------------------------

_STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}


def write_bag(path: str | Path, messages: Iterable[tuple[str, str, int, object]], *,
              storage: str = 'mcap', typestore: Typestore | None = None) -> int:
    """Write messages to a new rosbag2 directory.

    Parameters
    ----------
    path : str or Path
        The bag directory to create; it must not exist.
    messages : iterable of (topic, msgtype, stamp_ns, msg)
        ``msg`` is a message object of ``typestore`` (serialised here) or already
        serialised CDR ``bytes`` (e.g. from ``rclpy.serialization.serialize_message``).
        ``stamp_ns`` becomes the bag's receive time.
    storage : {'mcap', 'sqlite3'}, default='mcap'
    typestore : Typestore, optional
        Defaults to ``io.messages.get_typestore()``; it also gives the definitions embedded in
        the bag.

    Returns
    -------
    int
        Number of messages written.

    Raises
    ------
    BagReadError
        The path exists, or the storage is unknown, or rosbags cannot write.
    """
    path = Path(path)
    if storage not in _STORAGES:
        raise BagReadError(f'unknown bag storage {storage!r}; use mcap or sqlite3')
    if path.exists():
        raise BagReadError(f'{str(path)!r} exists already; not overwriting')
    store = typestore if typestore is not None else msgs.get_typestore()
    count = 0
    try:
        with Writer(path, version=Writer.VERSION_LATEST,
                    storage_plugin=_STORAGES[storage]) as writer:
            connections: dict[tuple[str, str], Connection] = {}
            for topic, msgtype, stamp, msg in messages:
                connection = connections.get((topic, msgtype))
                if connection is None:
                    connection = writer.add_connection(topic, msgtype, typestore=store)
                    connections[topic, msgtype] = connection
                if isinstance(msg, (bytes, bytearray, memoryview)):
                    data: bytes | memoryview = bytes(msg)
                else:
                    data = store.serialize_cdr(msg, msgtype)
                writer.write(connection, int(stamp), data)
                count += 1
    except (WriterError, OSError) as err:
        raise BagReadError(f'writing bag {str(path)!r}: {_reason(err)}') from err
    return count
