"""Run folders: the measured log, the true states and the metadata of one simulated (or lab) run.

A run folder (format ``exuflex-run/1``, specified in ``docs/run_format.md``) holds

- ``sensors.csv``: ``time`` then the measured motor torques (the observer's inputs) then the sensor
  channels, named as in the model file (six-bar: ``time,T1,T2,T3,q1,q2,q3,q3rel,c1,c2,c4,tip_x,tip_y``).
  An empty cell means "not sampled at this time" (a channel slower than the base rate);
- ``truth.csv``: ``time`` then the true states (``q1..``, ``dq1..``, tip elastic ``x25,y26,dx25,dy26``);
  optional (a lab run has none);
- ``meta.json``: engine, model file and its sha256, mechanism name, settings, seed, package versions,
  creation time, the unit of every column, and ``input_hold``: what the torques did between two samples
  (:data:`INPUT_HOLDS`, :func:`input_hold_of`).

Files are written atomically (temporary file in the same folder, then ``os.replace``). The readers
raise :class:`~exuflex.errors.LogFormatError` naming the file, the column or row, and what was expected.

Also here: :func:`read_csv_log` for a generic CSV log with a user channel mapping, and
:func:`read_exudyn_sensor` for Exudyn's own sensor output files.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import itertools
import json
import logging
import math
import os
import platform
import re
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from .errors import LogFormatError
from .sensors import Signals

__all__ = [
    "DELIMITER_NAMES",
    "FORMAT",
    "INPUT_HOLDS",
    "LogColumns",
    "Run",
    "SignalsCsvWriter",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_csv_dialect",
    "check_not_foreign",
    "dump_json",
    "file_sha256",
    "held_torques",
    "input_hold_of",
    "output_folder",
    "package_versions",
    "read_csv_log",
    "read_exudyn_sensor",
    "read_run",
    "read_signals_csv",
    "versions_text",
    "write_run",
    "write_signals_csv",
]

log = logging.getLogger(__name__)

FORMAT = "exuflex-run/1"
SENSORS_FILE, TRUTH_FILE, META_FILE = "sensors.csv", "truth.csv", "meta.json"
MANOEUVRE_FILE = "manoeuvre.toml"
"""The copy of the manoeuvre file a simulated run was made with (``exuflex simulate --manoeuvre``)."""
TIME = "time"
INPUT_HOLDS = ("zoh", "linear")
"""What a log's torques did between two samples (``meta.json``'s ``input_hold``): ``"zoh"``, each sample held to
the next (a digital controller's zero-order hold: a lab rig; a truth whose planned torque steps at samples);
``"linear"``, a smooth signal sampled, which the observer's step takes linear between the two samples
(:attr:`exuflex.observer.reduced.ReducedObserverModel.input_hold`), delayed by ``input_delay_s`` (a truth's
torque table held over its own step: half of it). A log without ``input_hold`` is "zoh" (every log before the
field existed was filtered so), without ``input_delay_s`` 0."""


def input_hold_of(meta: Mapping, where: str = META_FILE) -> tuple[str, float]:
    """The log's ``(input_hold, input_delay_s)`` (:data:`INPUT_HOLDS`; defaults "zoh" and 0); a
    :class:`~exuflex.errors.LogFormatError` naming ``where`` and the field if either is out of its range."""
    v = meta.get("input_hold", "zoh")
    if v not in INPUT_HOLDS:
        raise LogFormatError(f"{where}: field 'input_hold' must be one of {', '.join(map(repr, INPUT_HOLDS))} (what "
                             f"the torques did between two samples), got {v!r}")
    d = meta.get("input_delay_s", 0.0)
    if isinstance(d, bool) or not isinstance(d, (int, float)) or not (math.isfinite(d) and d >= 0):
        raise LogFormatError(f"{where}: field 'input_delay_s' must be a number of seconds >= 0 (how long after their "
                             f"samples the torques act), got {d!r}")
    return v, float(d)


@dataclass(frozen=True)
class Run:
    """A run read from disk: measured channels, true states (None for a lab run), metadata."""

    path: Path
    sensors: Signals  # time, measured torques, sensor channels
    truth: Signals | None
    meta: dict

    @property
    def motors(self) -> tuple[str, ...]:
        return tuple(self.meta.get("motors", ()))

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(self.meta.get("sensors", ()))

    @property
    def input_hold(self) -> tuple[str, float]:
        """What the torques did between two samples: ``("zoh" or "linear", delay in s)`` (:func:`input_hold_of`)."""
        return input_hold_of(self.meta, str(self.path / META_FILE) if self.path.is_dir() else str(self.path))

    @property
    def inputs(self) -> Signals:
        """The measured torques (observer inputs)."""
        return self.sensors.select(self.motors)

    @property
    def outputs(self) -> Signals:
        """The measured sensor channels."""
        return self.sensors.select(self.sensor_names)


# ------------------------------------------------------------------------------------------ writing
def _file_mode() -> int:
    """The mode ``open()`` gives a new file: 0666 less the process's umask (0644 under the usual 022)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` (flushed to disk), then rename it over ``path``:
    an interruption leaves either the old file or the new one, never a partial one."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, _FILE_MODE)  # mkstemp's 0600 would make results unreadable to others
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` as UTF-8 atomically, see :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _fmt(x: float) -> str:
    return "" if math.isnan(x) else repr(float(x))


class SignalsCsvWriter:
    """A CSV of ``time`` plus the channels ``names`` written a block of rows at a time (:meth:`write`), as
    :func:`write_signals_csv` writes a whole table (full precision, NaN as an empty cell, the same bytes),
    atomically: the rows go to a temporary file beside ``path`` that :meth:`close` flushes to disk and renames
    over it; :meth:`abort` (or leaving the ``with`` block by an exception) removes it and leaves ``path`` as it
    was. Only the block being written is held in memory."""

    def __init__(self, path: str | os.PathLike, names: Sequence[str]):
        self.path = Path(path)
        self.names = tuple(names)
        fd, self._tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        try:
            os.fchmod(fd, _FILE_MODE)  # mkstemp's 0600 would make results unreadable to others
            self._f = os.fdopen(fd, "w", encoding="utf-8", newline="\n")
        except BaseException:
            os.close(fd)
            os.unlink(self._tmp)
            raise
        self._f.write(",".join((TIME,) + self.names) + "\n")

    def write(self, sig: Signals) -> None:
        """Append the rows of ``sig`` (its channels must be ``names``, in order)."""
        if sig.names != self.names:
            raise ValueError(f"{self.path}: rows with channels {sig.names}, the file has {self.names}")
        for a in range(0, len(sig.t), 4096):  # the text of a few thousand rows at a time
            self._f.write("".join(",".join([repr(float(sig.t[k]))] + [_fmt(v) for v in sig.data[k]]) + "\n"
                                  for k in range(a, min(a + 4096, len(sig.t)))))

    def close(self) -> None:
        """Flush the file to disk and rename it over ``path``."""
        try:
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        """Remove the temporary file (``path`` is left as it was)."""
        self._f.close()
        if os.path.exists(self._tmp):
            os.unlink(self._tmp)

    def __enter__(self) -> SignalsCsvWriter:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()


def write_signals_csv(path: str | os.PathLike, sig: Signals) -> None:
    """Write ``time`` plus the channels of ``sig`` as CSV (full precision; NaN as an empty cell), atomically
    (:class:`SignalsCsvWriter`)."""
    with SignalsCsvWriter(path, sig.names) as w:
        w.write(sig)


def package_versions() -> dict[str, str | None]:
    """Installed versions of the packages a run depends on (None if absent)."""
    out: dict[str, str | None] = {}
    for name in ("numpy", "scipy", "filterpy", "exudyn", "exuflex"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def versions_text() -> str:
    """``"numpy 2.1.3, scipy 1.14.1, ..., python 3.11.7"``: :func:`package_versions` and Python's, for a page a
    benchmark writes."""
    return ", ".join(f"{k} {v}" for k, v in {**package_versions(), "python": platform.python_version()}.items())


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 16), b""):
            h.update(chunk)
    return h.hexdigest()


def write_run(
    out_dir: str | os.PathLike,
    sensors: Signals,
    truth: Signals | None,
    meta: Mapping,
    *,
    motors: Sequence[str] = (),
) -> Path:
    """Write a run folder (created if needed); returns its path.

    Parameters
    ----------
    out_dir : path
    sensors : Signals
        Measured torques then sensor channels.
    truth : Signals or None
        True states (same or different time grid).
    meta : mapping
        Run metadata (engine, model, settings, seed, ``input_hold``, ...); ``format``, ``created``, ``versions``,
        ``motors``, ``sensors``, ``truth`` and ``units`` are filled in if absent, ``input_hold`` with its default
        (:func:`input_hold_of`).
    motors : sequence of str
        Which columns of ``sensors`` are measured torques (default: ``meta['motors']``).
    """
    out = _path_argument(out_dir, "out_dir")
    check_not_foreign(out, "out_dir")  # never over a lab's own data
    out.mkdir(parents=True, exist_ok=True)
    # overwriting a run: mark the folder incomplete first, so an interruption cannot leave new data
    # files beside the old meta.json (a folder with a meta.json is complete)
    (out / META_FILE).unlink(missing_ok=True)
    meta = dict(meta)
    motors = tuple(motors or meta.get("motors", ()))
    missing = [m for m in motors if m not in sensors.names]
    if missing:
        raise ValueError(
            f"write_run: motor column(s) {missing} not in the sensor channels {list(sensors.names)}"
        )
    meta["input_hold"], meta["input_delay_s"] = input_hold_of(meta, "write_run: meta")
    meta.setdefault("format", FORMAT)
    meta.setdefault("created", _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))
    meta.setdefault("versions", package_versions())
    meta["motors"] = list(motors)
    meta["sensors"] = [n for n in sensors.names if n not in motors]
    meta["truth"] = list(truth.names) if truth is not None else []
    units = {
        SENSORS_FILE: {TIME: "s", **dict(zip(sensors.names, sensors.units or [""] * len(sensors.names)))}
    }
    if truth is not None:
        units[TRUTH_FILE] = {TIME: "s", **dict(zip(truth.names, truth.units or [""] * len(truth.names)))}
    meta["units"] = units
    write_signals_csv(out / SENSORS_FILE, sensors)
    if truth is not None:
        write_signals_csv(out / TRUTH_FILE, truth)
    elif (out / TRUTH_FILE).exists():
        os.unlink(out / TRUTH_FILE)  # a stale truth would not belong to this run
    # meta last: a folder with a meta.json is complete
    atomic_write_text(out / META_FILE, dump_json(meta, indent=2) + "\n")
    if _read_mark(out) is None or isinstance(_read_mark(out).get("files"), list):
        _seal(out, "write_run")  # a folder write_run wrote alone (no command's block around it) is exuflex's
    return out


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"meta: cannot store {type(o).__name__} in JSON")


# ------------------------------------------------------------------------------------------ output folders
OUTPUT_MARK = ".exuflex.json"
"""The mark exuflex leaves in every folder it writes: the command that wrote it and the entries it wrote
(``files``; ``null`` while a command is writing, when everything in the folder is the command's)."""

_RUN_ENGINES = ("exudyn", "erls", "reduced")


_OUTPUT_NAMES = re.compile(r"^(fig_[\w.-]*\.png|[\w-]*\.gif|estimates\.csv|results?\.(csv|json)|summary\.json|"
                           r"report\.md|plan\.csv|table2\.json)$")
"""Names of the files exuflex's library writes into a folder beside a command's (figures drawn after a study,
a run's estimates): in a folder with exuflex's mark they are exuflex's."""


def _output_name(name: str) -> bool:
    return bool(_OUTPUT_NAMES.match(name))


def _is_temporary(name: str) -> bool:
    return name.startswith(".") and name.endswith(".tmp")  # an atomic write's temporary file


def _read_mark(folder: Path) -> dict | None:
    try:
        mark = json.loads((folder / OUTPUT_MARK).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return mark if isinstance(mark, dict) and mark.get("written_by") == "exuflex" else None


def _legacy_owner(folder: Path) -> str | None:
    """The command that wrote a folder of an exuflex version before the mark, recognised by its own record: a run
    folder's ``meta.json`` of an exuflex truth engine, a study's ``study.json``; else None."""
    try:
        meta = json.loads((folder / META_FILE).read_text(encoding="utf-8"))
        if isinstance(meta, dict) and meta.get("format") == FORMAT and meta.get("engine") in _RUN_ENGINES \
                and isinstance(meta.get("versions"), dict) and meta["versions"].get("exuflex"):
            return "simulate"
    except (OSError, ValueError):
        pass
    try:
        rec = json.loads((folder / "study.json").read_text(encoding="utf-8"))
        if isinstance(rec, dict) and str(rec.get("format", "")).startswith("exuflex-study/"):
            return "study"
    except (OSError, ValueError):
        pass
    return None


def _entries(folder: Path) -> list[str]:
    return sorted(e.name for e in folder.iterdir() if e.name != OUTPUT_MARK and not _is_temporary(e.name))


def _owner(folder: Path) -> tuple[str | None, list[str]]:
    """``(command, foreign entries)`` of an existing folder: the exuflex command that wrote it (None: not exuflex's
    or empty) and the entries exuflex did not write."""
    entries = _entries(folder)
    mark = _read_mark(folder)
    if mark is not None:
        files = mark.get("files")
        foreign = [e for e in entries if e not in files and not _output_name(e)] if isinstance(files, list) else []
        return str(mark.get("command", "?")), foreign
    if not entries:
        return None, []
    owner = _legacy_owner(folder)
    return (owner, []) if owner else (None, entries)


def _listed(names: Sequence[str]) -> str:
    shown = ", ".join(names[:4])
    return shown + (f" and {len(names) - 4} more" if len(names) > 4 else "")


def check_not_foreign(folder: str | os.PathLike, param: str = "out_dir") -> None:
    """Raise a :class:`~exuflex.errors.UsageError` if ``folder`` is a file, or an existing folder holding anything
    exuflex did not write (a lab's measured log, a hand-written ``meta.json``): exuflex never writes over those."""
    from .errors import UsageError

    p = Path(folder)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{param}: {p} is a file, expected a folder (new, empty, or written by exuflex)")
    if p.is_dir():
        _, foreign = _owner(p)
        if foreign:
            raise UsageError(f"{param}: {p} holds files exuflex did not write ({_listed(foreign)}); expected a new or "
                             "empty folder, or one exuflex wrote: nothing there is touched")


def _write_mark(folder: Path, command: str, files: list[str] | None) -> None:
    from . import __version__

    atomic_write_text(folder / OUTPUT_MARK, dump_json(
        {"written_by": "exuflex", "version": __version__, "command": command, "files": files,
         "updated": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}) + "\n")


def _seal(folder: Path, command: str) -> None:
    """Record what the folder holds now as exuflex's (the command finished writing it)."""
    if folder.is_dir():
        _write_mark(folder, command, _entries(folder))


@contextmanager
def output_folder(path: str | os.PathLike, command: str, *, overwrite: bool = False, mode: str = "new",
                  param: str = "out (--out)", inputs: Sequence[str | os.PathLike] = ()) -> Iterator[Path]:
    """Claim the folder a command writes, before any work: the one rule of every command that writes a folder.

    - ``path`` a file (or below one): refused at once;
    - a new or empty folder: taken (created);
    - a folder holding anything exuflex did not write (no mark :data:`OUTPUT_MARK`, or entries the mark does not
      list: a lab's ``sensors.csv``, a ``meta.json`` of a measured run): refused, whatever ``overwrite`` says;
    - an earlier exuflex result: refused unless ``overwrite`` (then its entries are removed first), except
      ``mode="resume"`` on a folder the same ``command`` wrote (a study resumes) and ``mode="add"`` (files added
      beside an exuflex result: figures of a run).

    The block runs with the folder marked as being written by ``command``; leaving it normally records the
    entries as exuflex's; leaving it by an exception removes the folder if this call made it and it holds no
    result (nothing, or only hidden files such as a lock). ``inputs``: the files or folders the command reads; one of them inside the folder (or the folder
    itself) is refused, as the command would write over what it reads. Errors are
    :class:`~exuflex.errors.UsageError` naming ``param``.
    """
    from .errors import UsageError

    p = _path_argument(path, param)
    for src in inputs:
        a, b = Path(src).resolve(), p.resolve()
        if a == b or b in a.parents:
            raise UsageError(f"{param}: {p} holds the input {src}; expected another folder (the command would "
                             "write over what it reads)")
    if not isinstance(overwrite, bool):
        raise UsageError(f"overwrite (--overwrite): expected True or False, got {overwrite!r}")
    for a in [p, *p.parents]:
        if a.exists():
            if not a.is_dir():
                raise UsageError(f"{param}: {a} is a file, expected a folder" if a == p else
                                 f"{param}: {a} is a file, so {p} cannot be a folder")
            break
    made = not p.exists()
    keep: list[str] = []
    if not made:
        check_not_foreign(p, param)
        owner, _ = _owner(p)
        entries = _entries(p)
        if entries and owner is not None:
            if mode == "add" or (mode == "resume" and owner == command):
                keep, command = entries, owner  # the folder stays the earlier command's (a study resumes it)
            elif not overwrite:
                raise UsageError(f"{param}: {p} holds an earlier exuflex result (written by {owner}); pass "
                                 "--overwrite (overwrite=True) to replace it, or choose another folder")
            else:
                for name in entries:
                    e = p / name
                    if e.is_dir() and not e.is_symlink():
                        shutil.rmtree(e)
                    else:
                        e.unlink()
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{param}: cannot create {p} ({exc.strerror or exc})") from None
    if not os.access(p, os.W_OK):
        raise UsageError(f"{param}: {p} is not writable")
    _write_mark(p, command, None)
    try:
        yield p
    except BaseException:
        if made and p.is_dir() and all(e.startswith(".") for e in _entries(p)):  # nothing but a lock: as it was
            shutil.rmtree(p, ignore_errors=True)
        elif p.is_dir():
            _write_mark(p, command, sorted(set(keep) | set(_entries(p))))
        raise
    _seal(p, command)


def _json_safe(o):
    """``o`` with every non-finite float as None (JSON's ``null``), recursively; NumPy scalars and arrays, paths,
    tuples as their JSON forms."""
    if isinstance(o, (float, np.floating)):
        v = float(o)
        return v if math.isfinite(v) else None
    if isinstance(o, dict):
        return {str(k): _json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_json_safe(v) for v in o]
    if isinstance(o, np.ndarray):
        return _json_safe(o.tolist())
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, Path):
        return str(o)
    return o


def dump_json(obj, *, indent: int | None = 1, default=None) -> str:
    """Strict JSON text of ``obj`` (the one JSON writer of exuflex's files and ``--json`` output): undefined figures
    (NaN, infinities) as ``null``, NumPy values as numbers; another object through ``default`` (e.g. ``str``),
    else ``TypeError``. Strict parsers read it: it never holds a bare ``NaN`` or ``Infinity``."""

    def fallback(o):
        try:
            return _json_default(o)
        except TypeError:
            if default is None:
                raise
            return _json_safe(default(o))

    return json.dumps(_json_safe(obj), indent=indent, allow_nan=False, default=fallback)


# ------------------------------------------------------------------------------------------ reading
CHUNK_ROWS = 8192
"""Rows parsed at a time: the text held at once while reading a log (a few MB)."""


def _iter_lines(path: Path):
    """``(line number, text without its line end)`` of a UTF-8 text file, read lazily (one buffer at a time)."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise LogFormatError(f"{path}: is a folder, expected a text file")

    def gen():
        try:
            with open(path, encoding="utf-8-sig") as f:  # -sig: a byte-order mark (Excel) is not part of 'time'
                for i, ln in enumerate(f):
                    yield i + 1, ln.rstrip("\r\n")
        except UnicodeDecodeError as exc:
            raise LogFormatError(
                f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}); save the log as UTF-8 CSV"
            ) from None
        except OSError as exc:
            raise LogFormatError(f"{path}: cannot be read ({exc.strerror or exc})") from None

    return gen()


def _content_lines(path: Path, comment: str = "#"):
    """The lines of :func:`_iter_lines` that are neither blank nor comments, lazily."""
    return ((n, s) for n, s in _iter_lines(path) if s.strip() and not s.lstrip().startswith(comment))


def _read_lines(path: Path) -> list[tuple[int, str]]:
    """Every line of a (small) text file at once."""
    return list(_iter_lines(path))


def _parse_table(
    path: Path,
    lines: Sequence[tuple[int, str]],
    header: Sequence[str],
    *,
    allow_empty: bool,
    delimiter: str = ",",
    decimal: str = ".",
) -> np.ndarray:
    """Parse data lines (line number, text) into an (n, n_cols) float array with clear errors: the reference
    parser, cell by cell (Python's ``float`` on each stripped cell; an empty cell is NaN where allowed)."""
    n_col = len(header)
    data = np.empty((len(lines), n_col))
    for r, (lineno, text) in enumerate(lines):
        cells = [c.strip() for c in text.split(delimiter)]
        if len(cells) != n_col:
            raise LogFormatError(
                f"{path}: line {lineno}: {len(cells)} fields, expected {n_col} ({', '.join(header)})"
            )
        for c, cell in enumerate(cells):
            if cell == "":
                if allow_empty and c > 0:
                    data[r, c] = np.nan
                    continue
                raise LogFormatError(
                    f"{path}: line {lineno}, column {header[c]!r}: empty cell, expected a number"
                )
            try:
                if decimal != "." and "." in cell:
                    raise ValueError(cell)  # a decimal point where the decimal mark is another
                if "_" in cell:
                    raise ValueError(cell)  # Python's float reads '1_0' as 10: a number in a log has no '_'
                v = float(cell.replace(decimal, ".") if decimal != "." else cell)
            except ValueError:
                raise LogFormatError(
                    f"{path}: line {lineno}, column {header[c]!r}: {cell!r} is not a number"
                    + (f" (decimal mark {decimal!r})" if decimal != "." else "")
                ) from None
            if not math.isfinite(v):
                raise LogFormatError(
                    f"{path}: line {lineno}, column {header[c]!r}: {cell!r} is not a finite number"
                    + (" (leave the cell empty for 'not sampled')" if allow_empty and c > 0 else "")
                )
            data[r, c] = v
    return data


_EMPTY_CELL = {d: re.compile(rf"(^|{re.escape(d)})[ \t]*(?={re.escape(d)}|$)", re.M) for d in (",", ";", "\t", "|")}


def _parse_chunk(path: Path, lines: Sequence[tuple[int, str]], header: Sequence[str], *, allow_empty: bool,
                 delimiter: str, decimal: str) -> np.ndarray:
    """:func:`_parse_table` on a chunk of lines, through NumPy's compiled reader (``np.loadtxt``) when it gives
    the same numbers: it is stricter than ``float`` (it refuses what ``float`` also refuses, and a few forms
    ``float`` takes, such as ``1_0``), so any chunk it refuses, or in which it finds a non-finite value or an
    empty time, is parsed again by :func:`_parse_table`, which gives the value or the error message."""
    texts = [t for _, t in lines]
    n_col = len(header)
    joined = "\n".join(texts)
    literal_non_finite = any(ch in joined for ch in "nNiI")  # nan, inf: only the reference parser names them
    # every line with its field count (np.loadtxt strips a whitespace delimiter at a line's end: a tab-separated
    # line with one empty cell too many would pass)
    fields_ok = all(t.count(delimiter) == n_col - 1 for t in texts)
    if fields_ok and not literal_non_finite and (decimal == "." or "." not in joined) and (
            delimiter in _EMPTY_CELL or not allow_empty):
        if decimal != ".":
            joined = joined.replace(decimal, ".")
        d = delimiter
        if allow_empty and (d + d in joined or d + "\n" in joined or joined.endswith(d) or d + " " in joined
                            or d + "\t" in joined):  # an empty cell somewhere: NaN, as the reference parser
            joined = _EMPTY_CELL[d].sub(r"\1nan", joined)
        try:
            block = np.loadtxt(joined.splitlines(), delimiter=delimiter, dtype=float, ndmin=2, comments=None,
                               quotechar=None)
        except ValueError:
            block = None
        if block is not None and block.shape == (len(texts), n_col) and not np.isnan(block[:, 0]).any() \
                and not np.isinf(block).any() and (allow_empty or not np.isnan(block).any()):
            return block
    return _parse_table(path, lines, header, allow_empty=allow_empty, delimiter=delimiter, decimal=decimal)


def _parse_stream(path: Path, lines, header: Sequence[str], *, allow_empty: bool, delimiter: str = ",",
                  decimal: str = ".", size_bytes: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The data lines of an iterator ``(line number, text)`` as an ``(n, n_cols)`` float array and the line
    number of each row, read :data:`CHUNK_ROWS` lines at a time.

    Memory: the array is allocated once for the number of rows the file's size suggests (its size over the
    mean length of the first chunk's lines, plus 2 %) and grown by a quarter if the guess falls short, so the
    reader holds the array (8 bytes per cell, plus the row numbers), one chunk of text and, while growing, a
    second array; never the whole text.
    """
    n_col = len(header)
    data = np.empty((0, n_col))
    linenos = np.empty(0, np.int64)
    n = 0
    chunk: list[tuple[int, str]] = []

    def flush():
        nonlocal data, linenos, n
        block = _parse_chunk(path, chunk, header, allow_empty=allow_empty, delimiter=delimiter, decimal=decimal)
        m = len(block)
        if n + m > len(data):
            if n == 0 and size_bytes:
                per_line = max(1.0, sum(len(t) + 1 for _, t in chunk) / len(chunk))
                cap = max(n + m, int(size_bytes / per_line * 1.02) + 16)
            else:
                cap = max(n + m, int(len(data) * 1.25) + 16)
            grown = np.empty((cap, n_col))
            grown[:n] = data[:n]
            grown_ln = np.empty(cap, np.int64)
            grown_ln[:n] = linenos[:n]
            data, linenos = grown, grown_ln
        data[n : n + m] = block
        linenos[n : n + m] = [ln for ln, _ in chunk]
        n += m
        chunk.clear()

    for item in lines:
        chunk.append(item)
        if len(chunk) >= CHUNK_ROWS:
            flush()
    if chunk:
        flush()
    return data[:n], linenos[:n]


def _check_time(path: Path, t: np.ndarray, linenos: Sequence[int], column: str = TIME) -> None:
    if len(t) == 0:
        raise LogFormatError(f"{path}: no data rows (expected a header line and at least one row)")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise LogFormatError(
            f"{path}: column {column!r} is not strictly increasing at line {int(linenos[i])} "
            f"({float(t[i - 1])!r} then {float(t[i])!r})"
        )


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def read_signals_csv(
    path: str | os.PathLike,
    required: Sequence[str] = (),
    *,
    allow_empty: bool = False,
    units: Mapping[str, str] | None = None,
) -> Signals:
    """Read a ``time,...`` CSV written by :func:`write_signals_csv`.

    Lines starting with ``#`` and blank lines are skipped. Errors name the file, the column and the line. The
    file is read in chunks (:func:`_parse_stream`): the reader holds the returned array and one chunk of text.
    """
    path = Path(path)
    lines = _content_lines(path)
    first = next(lines, None)
    if first is None:
        raise LogFormatError(f"{path}: empty file (expected a header line 'time,...' and data rows)")
    header = [h.strip() for h in first[1].split(",")]
    if header[0] != TIME:
        raise LogFormatError(f"{path}: first column is {header[0]!r}, expected {TIME!r}")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise LogFormatError(f"{path}: duplicate column(s) {dup}")
    missing = [c for c in required if c not in header]
    if missing:
        raise LogFormatError(f"{path}: missing column(s) {missing}; the header has {header}")
    data, linenos = _parse_stream(path, lines, header, allow_empty=allow_empty, size_bytes=_size(path))
    _check_time(path, data[:, 0], linenos)
    names = tuple(header[1:])
    u = tuple((units or {}).get(n, "") for n in names)
    return Signals(data[:, 0], names, data[:, 1:], u)


def _path_argument(value, param: str) -> Path:
    """``value`` as a Path if it is a path (str or os.PathLike), else a UsageError naming the parameter."""
    from .errors import UsageError

    if isinstance(value, (str, os.PathLike)) and str(value).strip():
        return Path(value)
    raise UsageError(f"{param}: expected a path (str or pathlib.Path), got {type(value).__name__}"
                     + (" (already read: pass it on directly)" if isinstance(value, (Run, Signals)) else ""))


def read_run(run_dir: str | os.PathLike) -> Run:
    """Read a run folder written by :func:`write_run` (or by hand following ``docs/run_format.md``)."""
    d = _path_argument(run_dir, "run_dir")
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: run folder does not exist")
    mp = d / META_FILE
    if not mp.exists():
        raise FileNotFoundError(
            f"{mp}: missing (a run folder needs {META_FILE}, {SENSORS_FILE} and optionally {TRUTH_FILE})"
        )
    try:
        meta = json.loads(mp.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{mp}: not valid JSON ({exc})") from None
    except OSError as exc:
        raise LogFormatError(f"{mp}: cannot be read ({exc.strerror or exc})") from None
    if not isinstance(meta, dict):
        raise LogFormatError(f"{mp}: expected a JSON object")
    for key in ("motors", "sensors"):
        v = meta.get(key)
        if not isinstance(v, list) or not all(isinstance(x, str) and x for x in v):
            raise LogFormatError(f"{mp}: field {key!r} missing or not a list of column names, got {v!r}")
    tr = meta.get("truth", [])
    if tr is None:
        tr = []
    if not isinstance(tr, list) or not all(isinstance(x, str) and x for x in tr):
        raise LogFormatError(f"{mp}: field 'truth' is not a list of column names, got {tr!r}")
    units = meta.get("units", {})
    if units is None:
        units = {}
    if not isinstance(units, dict) or not all(isinstance(v, dict) for v in units.values()):
        raise LogFormatError(
            f"{mp}: field 'units' is not an object {{file: {{column: unit}}}}, got {units!r}"
        )
    input_hold_of(meta, str(mp))
    sensors = read_signals_csv(
        d / SENSORS_FILE, meta["motors"] + meta["sensors"], allow_empty=True, units=units.get(SENSORS_FILE)
    )
    # the torques are the observer's inputs: they must be sampled at every time
    for m in meta["motors"]:
        if np.isnan(sensors[m]).any():
            row = int(np.flatnonzero(np.isnan(sensors[m]))[0])
            raise LogFormatError(
                f"{d / SENSORS_FILE}: torque column {m!r} has an empty cell at data row {row + 1}"
            )
    truth = None
    if (d / TRUTH_FILE).exists():
        truth = read_signals_csv(d / TRUTH_FILE, tr, units=units.get(TRUTH_FILE))
    elif tr:
        raise FileNotFoundError(
            f"{d / TRUTH_FILE}: missing, but {META_FILE} lists truth columns {tr}"
        )
    return Run(d, sensors, truth, meta)


DELIMITER_NAMES = {"tab": "\t", "\\t": "\t", "comma": ",", "semicolon": ";", "space": " ", "pipe": "|"}
"""Names accepted for a delimiter that is awkward to type on a command line."""


def _shown(ch: str) -> str:
    return {"\t": "tab", " ": "space"}.get(ch, repr(ch))


def check_csv_dialect(delimiter: str, decimal: str = ".") -> None:
    """A CSV dialect :func:`read_csv_log` can read: the delimiter one character that cannot be part of a number
    (not a digit, sign, decimal point, exponent letter, quote, line end or ``#``), the decimal mark ``.`` or
    ``,``, and the two different. Else a :class:`~exuflex.errors.UsageError` naming ``--delimiter`` /
    ``--decimal``."""
    from .errors import UsageError

    if not isinstance(delimiter, str) or len(delimiter) != 1 or delimiter in "0123456789+-.eE\"'#\r\n" \
            or delimiter.isalnum():
        raise UsageError(f"delimiter (--delimiter): expected one character that is not part of a number, such as "
                         f"',', ';', '|' or tab, got {delimiter!r}")
    if decimal not in (".", ","):
        raise UsageError(f"decimal (--decimal): expected '.' or ',', got {decimal!r}")
    if decimal == delimiter:
        raise UsageError(f"decimal (--decimal): the decimal mark {decimal!r} is also the delimiter; expected "
                         "another delimiter (e.g. --delimiter ';' with --decimal ',')")


def read_csv_log(
    path: str | os.PathLike,
    channels: Mapping[str, str] | None = None,
    *,
    time_column: str = "time",
    time_scale: float = 1.0,
    delimiter: str = ",",
    decimal: str = ".",
    comment: str = "#",
    allow_empty: bool = True,
) -> Signals:
    """Read a generic CSV log with a header row, mapping its columns to exuflex channel names.

    Parameters
    ----------
    path : path
    channels : mapping, optional
        exuflex channel name -> column name in the file (e.g. ``{"q1": "enc1_rad", "T1": "motor1_Nm"}``);
        the result has the channels in the mapping's order. None keeps every column under its own name.
    time_column : str
        Name of the time column.
    time_scale : float
        Multiplies the time column (e.g. 1e-3 for milliseconds).
    delimiter, decimal, comment : str
        Field separator (one character, e.g. ``;`` or a tab), decimal mark (``.`` or ``,``, e.g. a European
        ``1,5;2,25``; not the delimiter), and the start of comment lines, which are skipped
        (:func:`check_csv_dialect`).
    allow_empty : bool
        Empty cells read as NaN (not sampled) instead of an error.

    Notes
    -----
    The file is read in chunks (:func:`_parse_stream`): the reader holds the parsed array, the mapped columns
    and one chunk of text, never the whole text.
    """
    from .errors import UsageError

    path = _path_argument(path, "path")
    check_csv_dialect(delimiter, decimal)
    if isinstance(time_scale, bool) or not isinstance(time_scale, (int, float)) or not (
        math.isfinite(time_scale) and time_scale > 0
    ):
        raise UsageError(f"time_scale (--time-scale): expected a positive number, got {time_scale!r}")
    lines = _content_lines(path, comment)
    first = next(lines, None)
    if first is None:
        raise LogFormatError(f"{path}: empty file (expected a header row and data rows)")
    header = [h.strip() for h in first[1].split(delimiter)]
    if len(header) == 1 and delimiter not in first[1]:
        other = [d for d in (",", ";", "\t", "|") if d != delimiter and d in first[1]]
        if other:
            raise LogFormatError(f"{path}: line {first[0]}: the header has no {_shown(delimiter)} but "
                                 f"{_shown(other[0])}; expected the delimiter {_shown(delimiter)} (--delimiter)")
    if time_column not in header:
        raise LogFormatError(f"{path}: no time column {time_column!r}; the header has {header} (name yours with "
                             "time_column=..., exuflex observe ... --time-column NAME)")
    mapping = dict(channels) if channels is not None else {h: h for h in header if h != time_column}
    missing = {ours: theirs for ours, theirs in mapping.items() if theirs not in header}
    if missing:
        raise LogFormatError(
            f"{path}: missing column(s) {list(missing.values())} (for channel(s) {list(missing)}); "
            f"the header has {header}"
        )
    used = list(dict.fromkeys([header.index(time_column)] + [header.index(c) for c in mapping.values()]))
    size = _size(path)
    if len(used) < len(header):  # columns not mapped (a status text, a spare channel): not parsed, named once
        unused = [h for i, h in enumerate(header) if i not in used]
        first_row = next(lines, None)
        if first_row is not None:
            cells = first_row[1].split(delimiter)
            text = [h for i, h in enumerate(header) if i not in used and i < len(cells)
                    and not _is_number(cells[i].strip(), decimal)]
            if text:
                log.warning("%s: column(s) %s not mapped to a channel and not numbers: ignored", path, text)
            else:
                log.info("%s: column(s) %s not mapped to a channel: ignored", path, unused)
            lines = itertools.chain([first_row], lines)
        lines = _select_cells(path, lines, used, len(header), delimiter, header)
        size = size * len(used) // len(header)
    sub = [header[i] for i in used]
    data, linenos = _parse_stream(path, lines, sub, allow_empty=allow_empty, delimiter=delimiter,
                                  decimal=decimal, size_bytes=size)
    if np.isnan(data[:, 0]).any():
        raise LogFormatError(f"{path}: empty cell in the time column {time_column!r}")
    t = data[:, 0] * time_scale
    _check_time(path, t, linenos, time_column)
    cols = [sub.index(c) for c in mapping.values()]
    return Signals(t, tuple(mapping), data[:, cols], ("",) * len(mapping))


def _is_number(cell: str, decimal: str = ".") -> bool:
    if cell == "":
        return True
    try:
        float(cell.replace(decimal, ".") if decimal != "." else cell)
    except ValueError:
        return False
    return True


def _select_cells(path: Path, lines, used: Sequence[int], n_col: int, delimiter: str, header: Sequence[str]):
    """The lines with only the cells of the columns ``used``, in that order (a line with another number of fields
    is named as :func:`_parse_table` names it)."""
    for lineno, text in lines:
        cells = text.split(delimiter)
        if len(cells) != n_col:
            raise LogFormatError(
                f"{path}: line {lineno}: {len(cells)} fields, expected {n_col} ({', '.join(header)})"
            )
        yield lineno, delimiter.join(cells[i] for i in used)


def read_lab_run(
    path: str | os.PathLike,
    mech,
    columns: Mapping[str, str] | None = None,
    *,
    time_column: str = "time",
    time_scale: float = 1.0,
    delimiter: str = ",",
    decimal: str = ".",
    truth: str | os.PathLike | None = None,
    columns_name: str = "columns",
    input_hold: str = "zoh",
) -> Run:
    """A lab's CSV log as a :class:`Run` of the mechanism ``mech``: what ``exuflex observe MODEL LOG.csv`` reads.

    ``columns`` maps the model's motor and sensor names to the log's column names (e.g. ``{"T1": "motor1_Nm",
    "q1": "enc1_rad"}``; a motor not listed is looked up under its own name; None: every channel under its own
    name); the other arguments as :func:`read_csv_log`. The log must have every motor's torque (the observer's
    input); its sensor columns are the channels it offers. ``truth``: an optional truth CSV (time column
    ``time``, columns named like the truth states) for the error metrics. ``columns_name`` names the argument
    in error messages (the command line's ``--map``). ``input_hold``: what the torques did between two samples
    (:data:`INPUT_HOLDS`; default "zoh", a digital controller's output held over its period)."""
    from .errors import UsageError
    from .mechanism import Mechanism

    path = _path_argument(path, "path")
    if not isinstance(mech, Mechanism):
        raise UsageError(f"mech: expected an exuflex.mechanism.Mechanism, got {type(mech).__name__}"
                         + (" (a path: load it with exuflex.load_mechanism(path) first)"
                            if isinstance(mech, (str, os.PathLike)) else ""))
    if columns is not None and not isinstance(columns, Mapping):
        raise UsageError(f"{columns_name}: expected a mapping {{channel: column}}, got {type(columns).__name__}")
    if truth is not None:
        truth = _path_argument(truth, "truth")
    motors = list(mech.motor_names)
    names = motors + [s.name for s in mech.sensors]
    mapping = None
    if columns is not None:
        mapping = {}
        for ours, theirs in dict(columns).items():
            if ours not in names:
                raise LogFormatError(f"{columns_name}: {ours!r} is not a motor or sensor of {mech.name}; expected "
                                     f"one of {names}")
            mapping[ours] = theirs
        for m in motors:
            mapping.setdefault(m, m)
        by_column: dict[str, list[str]] = {}
        for ours, theirs in mapping.items():
            by_column.setdefault(theirs, []).append(ours)
        twice = {col: chans for col, chans in by_column.items() if len(chans) > 1}
        if twice:
            col, chans = next(iter(twice.items()))
            raise LogFormatError(f"{columns_name}: the column {col!r} is mapped to the channels {chans}; expected "
                                 "one column per channel (each channel its own sensor)")
    if mapping is None:  # every channel of the model under its own name; the log's other columns are not read
        check_csv_dialect(delimiter, decimal)
        first = next(_content_lines(path), None)
        header = [h.strip() for h in first[1].split(delimiter)] if first is not None else []
        if header and time_column in header:
            mapping = {n: n for n in names if n in header}  # a missing torque: named below
    sig = read_csv_log(path, mapping, time_column=time_column, time_scale=time_scale, delimiter=delimiter,
                       decimal=decimal)
    have = [m for m in motors if m in sig]
    if len(have) != len(motors):
        raise LogFormatError(f"{path}: the observer needs the measured torques {motors}; the log has "
                             f"{list(sig.names)} (map your columns with {columns_name})")
    tr = read_csv_log(truth, time_column="time", delimiter=delimiter, decimal=decimal) if truth else None
    sensors = [n for n in sig.names if n not in motors and n in names]
    meta = {"engine": "csv", "source": str(path), "motors": motors, "sensors": sensors, "input_hold": input_hold}
    input_hold_of(meta, "input_hold")
    return Run(Path(path), sig, tr, meta)


def read_exudyn_sensor(path: str | os.PathLike, names: Sequence[str] | None = None) -> Signals:
    """Read an Exudyn sensor output file (text; ``#`` comment header; rows ``time,v1,v2,...``).

    Parameters
    ----------
    path : path
    names : sequence of str, optional
        Channel names of the value columns; default ``v0, v1, ...``.

    Notes
    -----
    Rows with a repeated time (Exudyn writes the initial state twice in some solvers) keep the last
    one. Binary sensor files (``sensorsWriteFileBinary``) are not supported.
    """
    path = Path(path)
    raw = _read_lines(path)  # Exudyn sensor files are short (one per sensor and run)
    if raw and "\x00" in raw[0][1]:
        raise LogFormatError(f"{path}: looks binary; write Exudyn sensor files as text")
    lines = [(n, s) for n, s in raw if s.strip() and not s.lstrip().startswith("#")]
    if not lines:
        raise LogFormatError(f"{path}: no data rows (expected Exudyn sensor rows 'time,values...')")
    n_col = len(lines[0][1].split(","))
    if n_col < 2:
        raise LogFormatError(f"{path}: line {lines[0][0]}: expected 'time,value[,value...]'")
    names = tuple(names) if names is not None else tuple(f"v{i}" for i in range(n_col - 1))
    if len(names) != n_col - 1:
        raise LogFormatError(
            f"{path}: {n_col - 1} value column(s), but {len(names)} names given: {list(names)}"
        )
    header = (TIME,) + names
    data = _parse_table(path, lines, header, allow_empty=False)
    keep = np.append(np.diff(data[:, 0]) != 0, True)  # drop repeated times, keep the last
    if not keep.all():
        log.debug("%s: dropped %d rows with a repeated time", path, int((~keep).sum()))
    data = data[keep]
    lines = [ln for ln, k in zip(lines, keep, strict=True) if k]
    _check_time(path, data[:, 0], [n for n, _ in lines])
    return Signals(data[:, 0], names, data[:, 1:], ("",) * len(names))


class LogColumns:
    """Columns of a log's table, a block of rows at a time: ``cols[a:b]`` is the ``(b - a, k)`` array of the
    columns ``cols`` of ``data`` (n, c) in rows ``a`` to ``b``, a copy of those rows only (the whole selection is
    never copied). :meth:`of` selects a :class:`Signals`' columns by name.

    ``hold``: a non-finite value is replaced by the column's last finite value before it, and by its first one
    before that (a torque not sampled at a time is held, ``docs/run_format.md``); a column without a finite value
    is an error naming it."""

    def __init__(self, data: np.ndarray, cols: Sequence[int], names: Sequence[str] | None = None,
                 hold: bool = False):
        self._data = data
        self.cols = [int(c) for c in cols]
        self.names = tuple(names) if names is not None else tuple(str(c) for c in self.cols)
        self.hold = bool(hold)
        self._prev: tuple[int, np.ndarray] | None = None
        if self.hold:
            first = np.empty(len(self.cols))
            for j, c in enumerate(self.cols):
                ok = np.flatnonzero(np.isfinite(data[:, c]))
                if not len(ok):
                    raise ValueError(f"torque column {self.names[j]} has no finite sample")
                first[j] = data[ok[0], c]
            self._first = first

    @classmethod
    def of(cls, signals: Signals, names: Sequence[str], hold: bool = False) -> LogColumns:
        """The columns ``names`` of ``signals`` (KeyError naming the missing ones, as :meth:`Signals.select`)."""
        names = tuple(names)
        cols = [signals.names.index(n) if n in signals.names else None for n in names]
        missing = [n for n, c in zip(names, cols, strict=True) if c is None]
        if missing:
            raise KeyError(f"no channel(s) {missing}; channels are {list(signals.names)}")
        return cls(signals.data, cols, names, hold)

    def __len__(self) -> int:
        return len(self._data)

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self._data), len(self.cols))

    def __getitem__(self, rows: slice) -> np.ndarray:
        a, b, step = rows.indices(len(self._data))
        if step != 1:
            raise IndexError("LogColumns: contiguous rows only")
        block = self._data[a:b, self.cols]
        if not self.hold:
            return block
        prev = self._prev[1] if self._prev is not None and self._prev[0] == a else self._before(a)
        bad = ~np.isfinite(block)
        if bad.any():
            for j in np.flatnonzero(bad.any(axis=0)):
                col = block[:, j]
                ok = np.isfinite(col)
                idx = np.where(ok, np.arange(len(col)), -1)
                np.maximum.accumulate(idx, out=idx)
                col[:] = np.where(idx >= 0, col[np.maximum(idx, 0)], prev[j])
        if b > a:
            self._prev = (b, block[-1].copy())
        return block

    def _before(self, a: int) -> np.ndarray:
        """Per column, the held value entering row ``a``: the last finite value before it, else the first."""
        out = self._first.copy()
        for j, c in enumerate(self.cols):
            ok = np.flatnonzero(np.isfinite(self._data[:a, c]))
            if len(ok):
                out[j] = self._data[ok[-1], c]
        return out


def held_torques(U: np.ndarray) -> np.ndarray:
    """A torque table (n, k) with its non-finite values held (:class:`LogColumns` with ``hold``), a copy."""
    U = np.asarray(U, float)
    return LogColumns(U, range(U.shape[1]), hold=True)[0 : len(U)]
