"""Logs are read in chunks (exuflex.runs._parse_stream) with NumPy's compiled reader where it gives the reference
parser's numbers; lab CSV dialects (--delimiter, --decimal)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from exuflex import runs
from exuflex.cli import main
from exuflex.errors import LogFormatError, UsageError
from exuflex.runs import _parse_chunk, _parse_table, check_csv_dialect, read_csv_log, read_signals_csv

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "tests" / "data" / "sixbar_erls_3s"
SIXBAR = str(ROOT / "models" / "sixbar.toml")

CELL = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.text(alphabet="0123456789.eE+-_ \tnaifNAIF,;x", max_size=6),
    st.sampled_from(["", " ", "nan", "inf", "-Infinity", "1_0", "1e5", ".5", "5.", "1,5", "0x1"]),
)


def _outcome(fn):
    try:
        return ("ok", fn())
    except LogFormatError as exc:
        return ("error", str(exc))


@settings(max_examples=200, deadline=None)
@given(rows=st.lists(st.lists(CELL, min_size=3, max_size=3), min_size=1, max_size=6),
       allow_empty=st.booleans(), dialect=st.sampled_from([(",", "."), (";", "."), (";", ","), ("\t", "."),
                                                           ("|", ",")]))
def test_compiled_chunk_reader_equals_the_reference_parser(rows, allow_empty, dialect):
    """The chunk reader gives the reference parser's numbers (bit for bit, NaN where empty) or its error."""
    delimiter, decimal = dialect
    header = ("time", "a", "b")
    lines = [(i + 2, delimiter.join(r)) for i, r in enumerate(rows)]
    kw = dict(allow_empty=allow_empty, delimiter=delimiter, decimal=decimal)
    fast = _outcome(lambda: _parse_chunk(Path("x.csv"), lines, header, **kw))
    ref = _outcome(lambda: _parse_table(Path("x.csv"), lines, header, **kw))
    assert fast[0] == ref[0]
    if fast[0] == "ok":
        assert fast[1].shape == ref[1].shape
        assert np.array_equal(fast[1], ref[1], equal_nan=True)
        assert np.array_equal(np.signbit(fast[1]), np.signbit(ref[1]))
    else:
        assert fast[1] == ref[1]


def _write(path: Path, header, data, delimiter=",", decimal=".", empty=()):
    lines = [delimiter.join(header)]
    for k, row in enumerate(data):
        cells = ["" if (k, j) in empty else repr(float(v)) for j, v in enumerate(row)]
        lines.append(delimiter.join(c.replace(".", decimal) for c in cells))
    path.write_text("\n".join(lines) + "\n")


def test_errors_in_later_chunks_name_their_line(tmp_path, monkeypatch):
    monkeypatch.setattr(runs, "CHUNK_ROWS", 7)
    rng = np.random.default_rng(0)
    data = np.column_stack([0.002 * np.arange(50), rng.standard_normal((50, 2))])
    p = tmp_path / "s.csv"
    _write(p, ("time", "a", "b"), data, empty={(3, 1), (33, 2)})
    sig = read_signals_csv(p, allow_empty=True)
    ref = data.copy()
    ref[3, 1] = ref[33, 2] = np.nan
    assert np.array_equal(np.column_stack([sig.t, sig.data]), ref, equal_nan=True)
    text = p.read_text().splitlines()
    cells = text[40].split(",")
    text[40] = ",".join([cells[0], "abc", cells[2]])  # data row 40, line 41
    p.write_text("\n".join(text) + "\n")
    with pytest.raises(LogFormatError, match=r"s\.csv: line 41, column 'a': 'abc' is not a number"):
        read_signals_csv(p, allow_empty=True)
    data[45, 0] = data[44, 0]
    _write(p, ("time", "a", "b"), data)
    with pytest.raises(LogFormatError, match=r"not strictly increasing at line 47 "):
        read_signals_csv(p)


def test_reader_memory_is_the_array_plus_one_chunk(tmp_path, monkeypatch):
    """Stated bound: the parsed array and its row numbers (8 bytes a cell, 2 % spare) plus the text of one chunk
    of CHUNK_ROWS lines and its parse, a few times the chunk's size; the whole text is never held."""
    monkeypatch.setattr(runs, "CHUNK_ROWS", 1024)
    n, cols = 30_000, 13
    rng = np.random.default_rng(1)
    data = np.column_stack([0.002 * np.arange(n), rng.standard_normal((n, cols - 1))])
    p = tmp_path / "big.csv"
    _write(p, ("time",) + tuple(f"c{j}" for j in range(cols - 1)), data)
    size = p.stat().st_size
    line = size / (n + 1)
    tracemalloc.start()
    sig = read_signals_csv(p)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    held = 1.02 * n * (cols + 1) * 8
    assert peak <= held + 8 * 1024 * line, (peak, held, size)
    assert peak < size  # less than the text itself (the whole-file reader held it several times over)
    assert np.array_equal(sig.data, data[:, 1:])


def test_european_csv_reads_as_the_plain_one(tmp_path):
    rng = np.random.default_rng(2)
    data = np.column_stack([0.002 * np.arange(30), rng.standard_normal((30, 3))])
    header = ("t_s", "T1", "q1", "c1")
    plain, euro, tab = tmp_path / "plain.csv", tmp_path / "euro.csv", tmp_path / "tab.csv"
    _write(plain, header, data, empty={(4, 2)})
    _write(euro, header, data, delimiter=";", decimal=",", empty={(4, 2)})
    _write(tab, header, data, delimiter="\t", empty={(4, 2)})
    a = read_csv_log(plain, time_column="t_s")
    b = read_csv_log(euro, time_column="t_s", delimiter=";", decimal=",")
    c = read_csv_log(tab, time_column="t_s", delimiter="\t")
    for s in (b, c):
        assert s.names == a.names and np.array_equal(s.t, a.t) and np.array_equal(s.data, a.data, equal_nan=True)
    with pytest.raises(LogFormatError, match=r"euro\.csv: line 1: the header has no ',' but ';'; expected the "
                                             r"delimiter ',' \(--delimiter\)"):
        read_csv_log(euro, time_column="t_s")
    with pytest.raises(LogFormatError, match=r"euro\.csv: line 2, column 't_s': '0,0' is not a number"):
        read_csv_log(euro, time_column="t_s", delimiter=";")
    semi = tmp_path / "semi_dot.csv"  # ';' between cells, but '.' decimals: not the declared mark
    semi.write_text(plain.read_text().replace(",", ";"))
    with pytest.raises(LogFormatError, match=r"semi_dot\.csv: line 2, column 't_s': '0\.0' is not a number "
                                             r"\(decimal mark ','\)"):
        read_csv_log(semi, time_column="t_s", delimiter=";", decimal=",")


@pytest.mark.parametrize("delimiter,decimal,flag", [("ab", ".", "--delimiter"), ("1", ".", "--delimiter"),
                                                    (".", ".", "--delimiter"), ("e", ".", "--delimiter"),
                                                    (",", ";", "--decimal"), (",", ",", "--decimal")])
def test_bad_dialects(delimiter, decimal, flag):
    with pytest.raises(UsageError, match=f"^[a-z]+ \\({flag}\\): "):
        check_csv_dialect(delimiter, decimal)


@pytest.mark.parametrize("argv,phrase", [(["--delimiter", "ab"], "(--delimiter)"),
                                         (["--decimal", ","], "is also the delimiter"),
                                         (["--delimiter", "tab", "--decimal", "x"], "(--decimal)")])
def test_cli_dialect_errors_are_one_line(tmp_path, capsys, argv, phrase):
    log = tmp_path / "lab.csv"
    log.write_text((RUN / "sensors.csv").read_text())
    assert main(["observe", SIXBAR, str(log), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and phrase in err


def test_observe_and_plot_read_a_european_lab_csv(tmp_path, capsys):
    """The run folder's log written with ';' between cells and ',' as decimal mark: the command line's reader
    (shared by observe and plot) gives the run folder's numbers."""
    from exuflex.cli import _build_parser
    from exuflex.cli.observe import _read_log
    from exuflex.mechanism import load_mechanism
    from exuflex.runs import read_run

    euro = tmp_path / "euro.csv"
    lines = (RUN / "sensors.csv").read_text().splitlines()
    euro.write_text("\n".join(ln.replace(",", ";").replace(".", ",") for ln in lines) + "\n")
    mech = load_mechanism(SIXBAR)
    ref = read_run(RUN).sensors
    for cmd in ("observe", "plot"):
        args = _build_parser().parse_args([cmd, SIXBAR, str(euro), "--delimiter", "semicolon", "--decimal", ","])
        got = _read_log(args, mech).sensors
        assert got.names == ref.names and np.array_equal(got.t, ref.t) and np.array_equal(got.data, ref.data)
    assert main(["plot", SIXBAR, str(euro)]) == 2
    assert "the header has no ',' but ';'" in capsys.readouterr().err
