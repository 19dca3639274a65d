"""Lab data for `fit` and `diagnose`: the CSV of docs/csv.md, or an MCAP recording, as one SampleBlock.

Bad input is a DataError naming the file, line and column; nothing is guessed.
"""

from __future__ import annotations

import codecs
import math
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluxcal.drivers.block import FLAG_SATURATED, FLAG_TEMP_INVALID, FLAGS_RESERVED, SampleBlock
from fluxcal.drivers.errors import DataError
from fluxcal.drivers.inputs import read_text

_PROBE_COL = re.compile(r"^s([1-9][0-9]*)_(x|y|z|temp)$")

#: the largest magnitude of any value in a lab CSV: far beyond any field (Earth's is 5e4 nT; in fT 5e10), time
#: (s) or counter a file holds, and far below sqrt(max float) = 1.3e154, so that squares and products of squares
#: in the fits stay finite (1e308 on every row gave a LinAlgError traceback)
MAX_MAGNITUDE = 1e15
#: rows parsed at once (about 0.1 s each)
PARSE_ROWS = 1 << 18


@dataclass(frozen=True)
class LabData:
    """Samples plus what the file said about them."""

    block: SampleBlock
    probe_names: list[str]
    path: str
    comments: list[str] = field(default_factory=list)
    #: what reading lost or skipped (a recording cut by a killed writer, damaged records): said on stderr
    warnings: list[str] = field(default_factory=list)
    #: load_data(max_probe_samples=...): every k-th sample of the file kept (1: all), of n_read in the file
    every: int = 1
    n_read: int | None = None
    #: an MCAP recording's "fluxcal" metadata record (unit, probe_names, the service's stored config, ...)
    metadata: dict[str, str] = field(default_factory=dict)
    #: what a reader of another ecosystem's log did to put its streams on one time base (the time base, the
    #: matching, what has no temperature), for the notes of fit and diagnose (formats.py, numerics/merge.py)
    notes: list[str] = field(default_factory=list)

    @property
    def ref_total(self) -> np.ndarray | None:
        return self.block.extras.get("ref_total")


def check_time_increases(p: Path, block: SampleBlock) -> None:
    """A recording's samples in time order, as a CSV's must be: DataError naming the sample where time goes
    back (a unit restart or a repeated frame recorded by a fluxcal before 2026-12, whose drivers passed them on)."""
    back = np.flatnonzero(~(np.diff(block.t_s) > 0))
    if back.size:
        r = int(back[0]) + 1
        raise DataError(f"{p}: sample {r} (seq {int(block.seq[r])}): time {float(block.t_s[r])} s does not increase "
                        f"(previous {float(block.t_s[r - 1])} s, seq {int(block.seq[r - 1])}); {back.size} such "
                        f"step(s) in the recording; t must be strictly increasing (a unit restart or a repeated frame "
                        f"recorded as it came: fit the stretches before and after it separately)")


def check_one_run(p: Path) -> None:
    """A directory is read as one run of rotated MCAP files: one without any, or holding several runs (each
    starts with a -0001 file), is a DataError saying what to give instead."""
    files = sorted(f.name for f in p.glob("*.mcap") if f.is_file())
    if not files:
        raise DataError(f"{p}: is a directory without .mcap files (allowed: a .csv or .mcap file, or a directory of "
                        f"one run's rotated .mcap files)")
    starts = [f for f in files if f.endswith("-0001.mcap")]
    if len(starts) > 1:
        shown = ", ".join(starts[:4]) + (", ..." if len(starts) > 4 else "")
        raise DataError(f"{p}: holds {len(starts)} separate runs ({shown}): give one run (its -0001 file, or a "
                        f"directory of only its files)")


def keep_every(n: int, probes: int, max_samples: int | None, max_probe_samples: int | None) -> int:
    """The smallest k for which every k-th of n samples of `probes` probes stays within both limits (None or
    0: no limit)."""
    k = 1
    if max_samples:
        k = max(k, -(-n // int(max_samples)))
    if max_probe_samples:
        k = max(k, -(-n * probes // int(max_probe_samples)))
        while k < n and -(-n // k) * probes > int(max_probe_samples):    # ceil(n / k) rows are kept
            k += 1
    return k


def load_csv(path: str | Path) -> LabData:
    """Parse a lab CSV (docs/csv.md)."""
    p = Path(path)
    # a regular file within the size and line limits, read in pieces (SIGTERM stops it), its first piece judged
    # before the next is read (garbage refused within it, whatever its size): fluxcal.drivers.inputs
    lines = read_text(p, "a lab CSV", head=_head_problem(p)).splitlines()
    comments: list[str] = []
    header_idx = _find_header(p, lines, comments)
    header = [h.strip() for h in lines[header_idx].split(",")]
    _check_header(p, header, header_idx + 1)         # 1-based line number of the header
    rows, lineno = _data_rows(p, lines, header_idx, comments)
    values = _parse_rows(p, header, rows, lineno)
    del rows, lines
    return lab_table(p, header, values, lineno, comments)


def lab_table(p: Path | str, header: list[str], values: np.ndarray, lineno: np.ndarray | None = None,
              comments: list[str] | None = None) -> LabData:
    """A lab CSV's columns (docs/csv.md: `header`, and `values` (N, columns) float) as LabData, checked as a CSV's
    are: every reader of such a table (a file, a pandas DataFrame, arrays: fluxcal.service.wiring.api) goes through here, so
    the same numbers give the same samples. lineno: each row's line in its file (for the messages), else 2, 3, ..."""
    values = np.array(values, dtype=np.float64)            # a copy: the caller's table is never changed
    lineno = np.arange(2, values.shape[0] + 2) if lineno is None else lineno
    _check_header(p, header, 1)
    if values.ndim != 2 or values.shape[1] != len(header) or values.shape[0] == 0:
        raise DataError(f"{p}: expected a table of rows by the {len(header)} columns of its header, got the shape "
                        f"{values.shape}")
    # a probe's axis or temperature may be NaN (or inf): saturated or invalid, left out by the fits and counted
    # there; any other column must be a number
    may_lack = np.array([bool(_PROBE_COL.match(h)) for h in header])
    _check_finite(p, header, values, lineno, may_lack)
    values[:, may_lack] = np.where(np.isfinite(values[:, may_lack]), values[:, may_lack], np.nan)
    _check_magnitude(p, header, values, lineno)
    col = {h: i for i, h in enumerate(header)}
    _check_time_column(p, values[:, col["t"]], lineno)
    block, n_probes = _csv_block(header, values)
    return LabData(block=block, probe_names=[f"s{k + 1}" for k in range(n_probes)], path=str(p),
                   comments=list(comments or []))


def _head_problem(p: Path):
    """The judge of a lab CSV's first piece (fluxcal.drivers.inputs.check_head): text, with the header and data rows a CSV
    has (each refused as the whole file's reading would refuse it, naming the line and column)."""
    def problem(head: bytes, whole: bool) -> str | None:
        try:
            text = codecs.getincrementaldecoder("utf-8-sig")().decode(head, final=whole)
        except UnicodeDecodeError as e:
            raise DataError(f"{p}: not a text file ({e.reason} at byte {e.start}): not a lab CSV") from None
        lines = text.splitlines()
        if not whole:
            lines = lines[:-1]                          # the last line may go on beyond the head
        if not whole and not any(ln.strip() and not ln.lstrip().startswith("#") for ln in lines):
            return None                                 # only comments so far: the header comes later
        i = _find_header(p, lines, [])
        header = [h.strip() for h in lines[i].split(",")]
        _check_header(p, header, i + 1)
        rows = [(k, ln) for k, ln in enumerate(lines[i + 1:], start=i + 2) if ln.strip() and not ln.lstrip()
                .startswith("#")]
        if rows:
            _parse_rows(p, header, [ln for _, ln in rows], np.array([k for k, _ in rows]))
        return None
    return problem


def _find_header(p: Path, lines: list[str], comments: list[str]) -> int:
    """The index of the header line: the first line neither blank nor a `#` comment; the comments before it
    are appended to `comments`. DataError if there is none."""
    for i, line in enumerate(lines):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s[1:].strip())
            continue
        return i
    raise DataError(f"{p}: no header line (expected e.g. 't,s1_x,s1_y,s1_z')")


def _data_rows(p: Path, lines: list[str], header_idx: int, comments: list[str]) -> tuple[list[str], np.ndarray]:
    """The data rows after the header and their 1-based line numbers (kept for error messages); a `#` line may
    come anywhere (an operator's note between two turns) and is appended to `comments`. DataError if no row."""
    body = [ln for ln in lines[header_idx + 1:]]
    rows_idx = []
    for j, ln in enumerate(body):
        s = ln.strip()
        if s.startswith("#"):
            comments.append(s[1:].strip())
        elif s:
            rows_idx.append(j)
    if not rows_idx:
        raise DataError(f"{p}: header but no data rows")
    rows = [body[j] for j in rows_idx] if len(rows_idx) != len(body) else body
    return rows, np.asarray(rows_idx) + header_idx + 2


def _parse_rows(p: Path, header: list[str], rows: list[str], lineno: np.ndarray) -> np.ndarray:
    """The rows as an (N, columns) float array; the first bad cell is a DataError naming its line and column."""
    ncol = len(header)
    values = np.empty((len(rows), ncol))
    for a in range(0, len(rows), PARSE_ROWS):   # in pieces: a signal's handler runs between them
        part_rows = rows[a:a + PARSE_ROWS]
        try:
            part = np.loadtxt(part_rows, delimiter=",", dtype=np.float64, ndmin=2, comments=None)
            if part.shape != (len(part_rows), ncol):
                raise ValueError
        except ValueError:
            _locate_bad_value(p, header, part_rows, lineno[a:a + PARSE_ROWS])
            raise DataError(f"{p}: could not parse the data rows") from None
        values[a:a + len(part_rows)] = part
    return values


def _check_finite(p: Path, header: list[str], values: np.ndarray, lineno: np.ndarray, may_lack: np.ndarray) -> None:
    """A non-finite value outside the columns that `may_lack` one (a probe's axes and temperature) is a
    DataError naming its line and column, and the other such lines."""
    bad = ~np.isfinite(values) & ~may_lack
    if bad.any():
        r, c = np.argwhere(bad)[0]
        rows = lineno[bad.any(axis=1)]
        more = f" and {rows.size - 10} more" if rows.size > 10 else ""
        raise DataError(f"{p}: line {lineno[r]}, column {header[c]!r}: {float(values[r, c])} is not a finite number; "
                        f"non-finite values on line(s) {', '.join(map(str, rows[:10].tolist()))}{more}: "
                        f"remove or fix those rows (only probe axes and temperatures may be NaN)")


def _check_time_column(p: Path, t: np.ndarray, lineno: np.ndarray) -> None:
    """The t column strictly increasing, else a DataError naming the first line where it does not."""
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        r = back[0] + 1
        raise DataError(f"{p}: line {lineno[r]}, column 't': time {float(t[r])} does not increase "
                        f"(previous {float(t[r - 1])}); t must be strictly increasing")


def _csv_block(header: list[str], values: np.ndarray) -> tuple[SampleBlock, int]:
    """The checked values as a SampleBlock (probe columns into field and temperature, seq and flags into theirs,
    the flags honoured, any other column an extra) and the number of probes."""
    col = {h: i for i, h in enumerate(header)}
    t = values[:, col["t"]]
    n_probes = max(int(_PROBE_COL.match(h).group(1)) for h in header if _PROBE_COL.match(h))
    n = values.shape[0]
    field_nT = np.empty((n, n_probes, 3))
    temp_C = np.full((n, n_probes), np.nan)
    for k in range(n_probes):
        for a, axis in enumerate("xyz"):
            field_nT[:, k, a] = values[:, col[f"s{k + 1}_{axis}"]]
        tc = col.get(f"s{k + 1}_temp")
        if tc is not None:
            temp_C[:, k] = values[:, tc]
    extras = {h: values[:, i].copy() for h, i in col.items() if h != "t" and not _PROBE_COL.match(h)}
    seq = extras.pop("seq", None)
    flags = extras.pop("flags", None)
    if flags is not None:
        _honour_flags(flags.astype(np.uint8), field_nT, temp_C)
    block = SampleBlock(
        t_s=t.copy(),
        seq=seq.astype(np.int64) if seq is not None else np.arange(n, dtype=np.int64),
        field_nT=field_nT, temp_C=temp_C,
        flags=flags.astype(np.uint8) if flags is not None else np.zeros(n, np.uint8),
        extras=extras,
    )
    return block, n_probes


def _check_magnitude(p: Path, header: list[str], values: np.ndarray, lineno: np.ndarray) -> None:
    """A value beyond MAX_MAGNITUDE (NaN is not) is a DataError naming its line and column, and the others'."""
    big = (values > MAX_MAGNITUDE) | (values < -MAX_MAGNITUDE)
    if not big.any():
        return
    r, c = np.argwhere(big)[0]
    rows = lineno[big.any(axis=1)]
    more = f" and {rows.size - 10} more" if rows.size > 10 else ""
    bound = f"{MAX_MAGNITUDE:g}".replace("e+", "e")
    raise DataError(f"{p}: line {lineno[r]}, column {header[c]!r}: {float(values[r, c]):.10g} is beyond the largest "
                    f"magnitude read, {bound} (allowed: |value| <= {bound}, so that squares in "
                    f"the fits stay finite); such values on line(s) {', '.join(map(str, rows[:10].tolist()))}{more}: "
                    f"no field, time or count is this large (an overflow, or a wrong unit in the export?)")


def _honour_flags(flags: np.ndarray, field_nT: np.ndarray, temp_C: np.ndarray) -> None:
    """The ICD flags column, in place: a temperature flagged invalid (bit1) is NaN; a sample with a reserved bit
    (3..7; bit 7 is fluxcal's implausible flag) is NaN throughout; in a sample flagged
    saturated (bit0) the saturated axes are NaN. Those are the axes already NaN or, in a file that wrote the
    rails as numbers (counts 2147483647 or -2147483648 times lsb_nT), at the largest magnitude of the flagged
    samples where more than one axis holds it (a rail repeats, a measurement does not); a flagged sample with
    neither is NaN for every probe (the flag does not say which axis)."""
    temp_C[(flags & FLAG_TEMP_INVALID) != 0] = np.nan
    implausible = (flags & FLAGS_RESERVED) != 0             # flagged by fluxcal's driver, or bits the ICD says are 0
    field_nT[implausible] = np.nan
    temp_C[implausible] = np.nan
    sat = (flags & FLAG_SATURATED) != 0
    if not sat.any():
        return
    f = field_nT[sat]                                        # (M, P, 3), a copy
    known = np.isnan(f).any(axis=(1, 2))
    mag = np.abs(np.where(np.isnan(f), 0.0, f))
    rail = float(mag[~known].max()) if (~known).any() else 0.0
    # the two rails differ by one count in 2^31 (5e-10): one magnitude to within 1e-6 is one rail
    at_rail = (mag >= rail * (1.0 - 1e-6)) & (rail > 0) & ~known[:, None, None]
    if np.count_nonzero(at_rail) < 2:
        # one axis at the largest magnitude is a measurement, not a rail (a rail repeats): the flag then does
        # not say which axis saturated, and the whole sample goes below
        at_rail[:] = False
    f[at_rail] = np.nan
    f[~np.isnan(f).any(axis=(1, 2))] = np.nan
    field_nT[sat] = f


def _check_header(p: Path, header: list[str], line_no: int) -> None:
    seen: set[str] = set()
    for h in header:
        if not h:
            raise DataError(f"{p}: line {line_no}: empty column name in the header")
        if h in seen:
            raise DataError(f"{p}: line {line_no}: column {h!r} appears twice")
        seen.add(h)
    if "t" not in seen:
        raise DataError(f"{p}: line {line_no}: no 't' column (time in seconds) in the header"
                        + _other_delimiter(p, ",".join(header)))
    probes = sorted({int(m.group(1)) for h in header if (m := _PROBE_COL.match(h))})
    if not probes:
        raise DataError(f"{p}: line {line_no}: no probe columns (expected s1_x, s1_y, s1_z, ...)")
    for k in range(1, probes[-1] + 1):
        for axis in "xyz":
            if f"s{k}_{axis}" not in seen:
                what = "probes must be numbered 1..N without gaps" if k not in probes else "missing axis"
                raise DataError(f"{p}: line {line_no}: column 's{k}_{axis}' is missing ({what})")


#: what a spreadsheet or LabVIEW writes between values in a locale with a decimal comma: how to say it, and how sed
#: writes it
OTHER_DELIMITERS = {";": ("';'", ";"), "\t": ("tabs", "\\t")}


def _other_delimiter(p: Path, header_line: str) -> str:
    """Why a header has no 't' column when it has one between ';' or tabs: what fluxcal reads and how to convert it
    (never read as it is: beside ';' a ',' may be a decimal comma or a thousands separator, 1,234 being 1.234 or
    1234, and a wrong guess would change every value without a word); '' for another header."""
    d = next((d for d in OTHER_DELIMITERS if "t" in (h.strip() for h in header_line.split(d))), None)
    if d is None:
        return ""
    said, sed = OTHER_DELIMITERS[d]
    if str(p).startswith("<"):                       # a table in memory (fluxcal.read of a pandas DataFrame)
        return (f": its column names are one name separated by {said}: read the file with sep={d!r} (and "
                f"decimal=',' where its numbers have a decimal comma)")
    into = f"{shlex.quote(str(p))} > {shlex.quote(str(p.with_name(p.stem + '-comma.csv')))}"
    return (f": the file is separated by {said}, and fluxcal reads values separated by ',' with '.' as the decimal "
            f"point (docs/csv.md). Export it so (a spreadsheet's list separator ',', decimal separator '.'), or "
            f"convert it: `sed 's/{sed}/,/g' {into}` where its numbers have a decimal point, "
            f"`sed 's/,/./g; s/{sed}/,/g' {into}` where they have a decimal comma (0,5)")


def _locate_bad_value(p: Path, header: list[str], rows: list[str], lineno: np.ndarray) -> None:
    """Slow path, only after the fast parse failed: find the first bad cell and raise there."""
    ncol = len(header)
    for r, line in enumerate(rows):
        cells = line.split(",")
        if len(cells) != ncol:
            other = next((d for d in (";", "\t") if line.count(d) >= ncol - 1), None)
            hint = (f"; values must be separated by ',' and this line uses {other!r}: a spreadsheet exported "
                    f"with another delimiter?" if other else "")
            raise DataError(f"{p}: line {lineno[r]}: {len(cells)} values, expected {ncol} (as in the header)"
                            f"{hint}")
        for c, cell in enumerate(cells):
            try:
                v = float(cell)
            except ValueError:
                blank = ""
                if not cell.strip():                # a table writer's missing value (pandas' to_csv writes '')
                    blank = (": a missing value is written nan, where it may be one (a probe's axis or temperature; "
                             "pandas: to_csv(na_rep='nan'))" if _PROBE_COL.match(header[c]) else
                             ": this column takes no missing value (docs/csv.md)")
                raise DataError(f"{p}: line {lineno[r]}, column {header[c]!r}: {cell.strip()!r} is not a number"
                                f"{blank}") from None
            if not math.isfinite(v) and not _PROBE_COL.match(header[c]):      # a probe's axis or temperature: NaN
                raise DataError(f"{p}: line {lineno[r]}, column {header[c]!r}: {cell.strip()!r} is not a finite number")
