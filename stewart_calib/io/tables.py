"""CSV text shared by the file readers and writers of :mod:`stewart_calib.io`.

Parsing is columnar: a fast path (``np.loadtxt``) for the common well-formed file and a careful
row-by-row path that finds and words the first problem of each bad row. Rows are numbered by
their 1-based line in the file (the header is line 1).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CalibError, without_noise
from ..inputs import MAX_STREAM_BYTES, read_input_bytes
from .atomic import atomic_path


def csv_text(header: list[str], columns: list, with_header: bool = True) -> str:
    """CSV text of equal-length columns; floats are written as the ``repr`` of their
    :func:`~stewart_calib.errors.without_noise` (15 significant digits: ``0.7``, not ``0.7000000000000001``).

    ``with_header=False``: the rows only (a block appended to a file written block by block).
    """
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    if with_header:
        writer.writerow(header)
    if len(columns) > 1 and all(map(_renderable, columns)):
        # the rows the csv module would write, rendered directly (a simulated truth file is 55
        # numbers a sample), a few thousand rows at a time so that only the text is held whole,
        # not a string object per field
        n = len(columns[0])
        for start in range(0, n, CSV_CHUNK_ROWS):
            buffer.write(_rows_text([c[start : start + CSV_CHUNK_ROWS] for c in columns]))
        return buffer.getvalue()
    rows = zip(*(without_noise(c.tolist() if isinstance(c, np.ndarray) else list(c)) for c in columns), strict=True)
    writer.writerows(rows)
    return buffer.getvalue()


#: rows :func:`csv_text` renders at a time.
CSV_CHUNK_ROWS = 4096


def _renderable(column) -> bool:
    """Numbers (an array, or floats, ints and empty strings), or text alone: columns :func:`_rows_text` renders."""
    if isinstance(column, np.ndarray):
        return column.dtype.kind in "fiu"
    return all(type(v) in (float, int) or (type(v) is str and v == "") for v in column) or all(
        type(v) is str for v in column
    )


def _rows_text(columns: list) -> str:
    """The CSV rows of a few rows of :func:`_renderable` columns, each ending in a line break."""
    parts, floats = [], []  # per row: the text of a run of float arrays, or one field
    for column in [*columns, None]:
        if isinstance(column, np.ndarray) and column.dtype.kind == "f":
            floats.append(column)
            continue
        if floats:
            parts.append(float_rows_csv(floats).decode().split("\n")[:-1])
            floats = []
        if column is not None:
            parts.append(_field_texts(column))
    rows = parts[0] if len(parts) == 1 else map(",".join, zip(*parts, strict=True))
    return "\n".join(rows) + "\n"


def _field_texts(column) -> list[str]:
    """A :func:`_renderable` column's fields as the csv module writes them in a row of several:
    ``repr`` of a float's :func:`~stewart_calib.errors.without_noise`, ``str`` of an int, text quoted
    where it must be."""
    values = column.tolist() if isinstance(column, np.ndarray) else column
    if values and all(type(v) is str for v in values):
        rendered = {value: _quoted(value) for value in set(values)}  # a few stage names over many rows
        return [rendered[v] for v in values]
    return [v if type(v) is str else repr(without_noise(v)) for v in values]


def write_csv_blocks(path: str | Path, header: list[str], blocks, blank: tuple[int, ...] = ()) -> int:
    """The file ``csv_text(header, columns)`` writes, byte for byte, from blocks of its float columns
    (a list of equal-length arrays per block of consecutive rows), written as they come: only a
    block is held however long the file. Columns whose index is in ``blank`` write a non-finite
    value as an empty field (a point target not seen), as ``csv_text`` writes ``""``.

    Atomic: the rows go to a temporary file beside ``path``, renamed onto it after the last block;
    an exception from ``blocks`` (a refused row) removes it and leaves ``path`` as it was. Returns
    the number of rows written.

    Raises:
        CalibError: the file cannot be written.
    """
    rows = 0
    large = False  # once a block holds a chunk, pyarrow writes every row after it, blocks' remainders too
    with atomic_path(path) as temporary, open(temporary, "wb") as file:
        file.write(csv_text(header, []).encode())
        for columns in blocks:
            large = large or len(columns[0]) >= CSV_CHUNK_ROWS
            for start in range(0, len(columns[0]), CSV_CHUNK_ROWS):
                file.write(float_rows_csv([c[start : start + CSV_CHUNK_ROWS] for c in columns], blank, large))
            rows += len(columns[0])
    return rows


def float_rows_csv(columns: list[np.ndarray], blank: tuple[int, ...] = (), large: bool = False) -> bytes:
    """The rows of equal-length float columns as :func:`csv_text` writes them (the ``repr`` of each
    float's :func:`~stewart_calib.errors.without_noise`, commas between, a line break after each row;
    see :func:`write_csv_blocks` for ``blank``), without the header; by pyarrow from
    :data:`CSV_CHUNK_ROWS` rows on, or for any rows of a ``large`` file: several times faster a row
    than ``repr`` on each field, its import (a tenth of a second, tens of MB) paying off
    (BENCHMARKS.md). ``large`` keeps a file written in blocks on pyarrow for each block's remainder
    too: by ``repr``, the remainders of a 10⁶-row import in blocks of ~5400 take a quarter of its time."""
    columns = [without_noise(np.asarray(column, dtype=float)) for column in columns]
    if len(columns[0]) < CSV_CHUNK_ROWS and not large:
        fields = [_repr_list(column, j in blank) for j, column in enumerate(columns)]
        return "".join(",".join(row) + "\n" for row in zip(*fields, strict=True)).encode()
    import pyarrow.compute as pc

    rows = pc.binary_join_element_wise(*(_repr_texts(column, j in blank) for j, column in enumerate(columns)), ",")
    rows = pc.binary_join_element_wise(rows, "", "\n")
    offsets = np.frombuffer(rows.buffers()[1], dtype=np.int32)[rows.offset : rows.offset + len(rows) + 1]
    return bytes(memoryview(rows.buffers()[2])[offsets[0] : offsets[-1]])


def _repr_list(values, blank: bool) -> list[str]:
    """Each float's ``repr``; with ``blank``, a non-finite one as ``""``."""
    return ["" if blank and not math.isfinite(v) else repr(v) for v in np.asarray(values, dtype=float).tolist()]


#: the magnitudes whose pyarrow text is ``repr``'s but for a whole number's ".0": both write the
#: shortest digits that read back to the float, positionally; outside, repr writes an exponent
#: from 1e-4 down and 1e16 up, pyarrow from ~1e-7 and wherever 17 digits pass 1e10 (e.g. 1.2e+10).
_POSITIONAL_MAGNITUDES = (1e-4, 1e9)


def _repr_texts(column: np.ndarray, blank: bool):
    """A float column's :func:`_repr_list` texts as a pyarrow string array."""
    import pyarrow as pa
    import pyarrow.compute as pc

    values = np.asarray(column, dtype=float)
    texts = pc.cast(pa.array(values), pa.string())
    magnitude = np.abs(values)
    positional = (magnitude >= _POSITIONAL_MAGNITUDES[0]) & (magnitude < _POSITIONAL_MAGNITUDES[1])
    whole = positional & (values == np.trunc(values))
    if whole.any():
        texts = pc.if_else(pa.array(whole), pc.binary_join_element_wise(texts, ".0", ""), texts)
    if not positional.all():
        others = _repr_list(values[~positional], blank)
        texts = pc.replace_with_mask(texts, pa.array(~positional), pa.array(others, pa.string()))
    return texts


def _quoted(text: str) -> str:
    """``text`` as a field of the csv module's rows: its writer's own quoting (of a row of two
    fields: a lone empty field is written ``""``)."""
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerow([text, ""])
    return buffer.getvalue()[: -len(",\n")]


def pose_columns_deg(poses: np.ndarray) -> list[np.ndarray]:
    """``(N, 6)`` poses [mm, rad] → six file columns [mm, deg]."""
    poses = np.asarray(poses, dtype=float)
    return [poses[:, 0], poses[:, 1], poses[:, 2], *np.degrees(poses[:, 3:]).T]


def read_text(path: Path, what: str) -> str:
    data = read_input_bytes(path, what, MAX_STREAM_BYTES)
    try:
        text = data.decode("utf-8-sig")  # a byte-order mark is what spreadsheet exports add
    except UnicodeDecodeError as err:
        raise CalibError(
            f"{path}: {what} is not UTF-8 text (byte 0x{data[err.start]:02x} at offset {err.start}); expected a UTF-8 "
            "CSV file"
        ) from None
    return text.replace("\r\n", "\n")


@dataclass
class Table:
    """Parsed CSV body: numeric columns as float arrays (NaN where unparsable), text columns
    as lists, the file line of each row, and the first problem found in each bad row."""

    numbers: dict[str, np.ndarray]
    texts: dict[str, list[str]]
    lines: np.ndarray
    issues: dict[int, str]

    def __len__(self) -> int:
        return len(self.lines)

    def flag(self, bad: np.ndarray, describe) -> None:
        """Record ``describe(k)`` for every row ``k`` in the mask that has no problem yet."""
        for k in np.flatnonzero(bad):
            self.issues.setdefault(int(k), describe(int(k)))


def read_header(path: Path, text: str) -> list[str]:
    """The column names in the first line of a file's ``text``.

    Raises:
        CalibError: an empty file, a header that is no CSV row, a name given twice.
    """
    if not text.strip():
        raise CalibError(f"{path}: empty file, no sample rows; expected a header row and at least one sample row")
    return header_fields(path, text.split("\n", 1)[0])


def header_fields(path: Path, first: str) -> list[str]:
    """The column names of a header line (see :func:`read_header`)."""
    try:
        header = [name.strip() for name in next(csv.reader([first]), [])]
    except csv.Error as err:  # e.g. a lone carriage return
        raise CalibError(f"{path}: row 1: expected a CSV header row ({err})") from None
    seen = set()
    for name in header:
        if name and name in seen:
            raise CalibError(f"{path}: row 1: column '{name}' appears twice; expected unique column names")
        seen.add(name)
    return header


def require_columns(path: Path, header: list[str], required) -> None:
    missing = [name for name in required if name not in header]
    if missing:
        raise CalibError(f"{path}: row 1: missing required column(s) {', '.join(missing)}")


#: how a refusal names the size of a group of columns (a pose's six, a direction's three)
_COUNT_WORDS = {2: "two", 3: "three", 6: "six"}


def optional_group(path: Path, header: list[str], group) -> bool:
    """True when all of ``group`` is present, False when none; a partial set is refused."""
    present = [name for name in group if name in header]
    if present and len(present) < len(group):
        missing = [name for name in group if name not in header]
        count = _COUNT_WORDS.get(len(group), str(len(group)))
        raise CalibError(
            f"{path}: row 1: columns {', '.join(group)} come all {count} or none; missing {', '.join(missing)}"
        )
    return bool(present)


#: bytes pyarrow parses at a time in :func:`numbers_by_arrow`: a quarter MB stays in the CPU's
#: cache (faster a row than parsing 4 MB in one go; BENCHMARKS.md).
ARROW_BLOCK_BYTES = 1 << 18


def numbers_by_arrow(header: list[str], data: bytes) -> Table | None:
    """The rows ``data`` (a file's bytes after its header, whole lines) when every field is a
    number, every column numeric: one float array per column by pyarrow's CSV reader straight
    from the bytes (~4× loadtxt's speed on one thread, correctly rounded like ``float``; no
    text decoded, split or joined again). Rows are numbered from line 2.

    None on any doubt, so the caller's path decides and words it: bytes other than ASCII (a
    UTF-8 check), a lone carriage return (a line break to pyarrow, not to the other paths),
    and whatever pyarrow does not read as a number — a quote, a blank line (an empty field to
    it), a field it cannot convert.
    """
    import pyarrow as pa
    import pyarrow.csv as pa_csv

    if not data.isascii() or (b"\r" in data and data.count(b"\r") != data.count(b"\r\n")):
        return None
    try:
        table = pa_csv.read_csv(
            pa.py_buffer(data),  # type: ignore[arg-type]  # it reads a Buffer too; the stubs list paths and files
            read_options=pa_csv.ReadOptions(column_names=header, use_threads=False, block_size=ARROW_BLOCK_BYTES),
            parse_options=pa_csv.ParseOptions(quote_char=False, ignore_empty_lines=False),
            convert_options=pa_csv.ConvertOptions(
                column_types={name: pa.float64() for name in header}, null_values=[], strings_can_be_null=False
            ),
        )
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None
    if any(column.null_count for column in table.columns):
        return None
    numbers = {name: column.to_numpy() for name, column in zip(header, table.columns, strict=True)}
    return Table(numbers, {}, np.arange(2, table.num_rows + 2), {})


def _parse_fast(header: list[str], text: str, numeric: list[str], textual: list[str]) -> Table | None:
    """The common case in C speed (``np.loadtxt``): no quoting, no blank lines, every field a number.

    Returns None when the file needs the careful path (which also finds the bad row).
    """
    if '"' in text:
        return None
    rows = text.split("\n")[1:]
    while rows and rows[-1] == "":
        rows.pop()
    commas = len(header) - 1
    # With every column numeric, loadtxt itself refuses a row of another field count (with
    # usecols it would take a longer row): the per-row count is only needed otherwise.
    every = set(numeric) == set(header)
    if not rows or (not every and any(row.count(",") != commas for row in rows)):
        return None
    index = {name: i for i, name in enumerate(header)}
    try:
        values = np.loadtxt(
            rows,
            delimiter=",",
            usecols=None if every else [index[name] for name in numeric],
            comments=None,
            ndmin=2,
            dtype=float,
        )
    except ValueError:
        return None
    # loadtxt skips a blank line (the careful path numbers rows around it) and takes rows that all
    # hold another field count than the header
    if values.shape != (len(rows), len(numeric)):
        return None
    numbers = {name: values[:, index[name] if every else j] for j, name in enumerate(numeric)}
    texts = {
        name: [
            v.strip() for v in np.loadtxt(rows, delimiter=",", usecols=[index[name]], comments=None, ndmin=1, dtype=str)
        ]
        for name in textual
    }
    return Table(numbers, texts, np.arange(2, len(rows) + 2), {})


def _floats(texts: tuple[str, ...], column: str, issues: dict[int, str], blank_is_nan: bool) -> np.ndarray:
    # Python's float reads "2_12.97" as 212.97: a digit separator is no CSV number (a typo, or a
    # locale's grouping), so such a field goes the careful way and is refused
    if not any("_" in text for text in texts):
        try:
            return np.array(texts, dtype=float)
        except ValueError:
            pass  # find the offending rows one by one below
    out = np.full(len(texts), np.nan)
    for k, text in enumerate(texts):
        try:
            if "_" in text:
                raise ValueError(text)
            out[k] = float(text)
        except ValueError:
            if not text.strip():
                if not blank_is_nan:
                    issues.setdefault(k, f"column '{column}': expected a number, got an empty field")
            else:
                issues.setdefault(k, f"column '{column}': expected a number, got {text!r}")
    return out


def parse_careful(header: list[str], text: str, numeric: list[str], textual: list[str], blank_is_nan) -> Table:
    """Row by row with the csv module: quoting, blank lines, wrong field counts, bad numbers."""
    reader = csv.reader(io.StringIO(text))
    next(reader, None)
    rows: list[list[str]] = []
    lines: list[int] = []
    issues: dict[int, str] = {}
    width = len(header)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as err:  # e.g. a lone carriage return inside a row; the reader goes on with the next line
            issues[len(rows)] = f"expected a CSV row ({err})"
            row = [""] * width
        if len(row) <= 1 and not (row and row[0].strip()):
            continue  # a blank line holds no sample
        if len(row) != width:
            issues[len(rows)] = f"expected {width} fields as in the header, got {len(row)}"
            row = [""] * width
        rows.append(row)
        lines.append(reader.line_num)
    columns = list(zip(*rows, strict=True)) if rows else [()] * width
    index = {name: i for i, name in enumerate(header)}
    numbers = {name: _floats(columns[index[name]], name, issues, name in blank_is_nan) for name in numeric}
    texts = {name: [field.strip() for field in columns[index[name]]] for name in textual}
    return Table(numbers, texts, np.array(lines, dtype=int), issues)


def parse_rows(header: list[str], text: str, numeric, textual=(), blank_is_nan=()) -> Table:
    """The rows of ``text`` (its first line is the header, skipped): the fast path, else the careful one."""
    numeric, textual = list(numeric), list(textual)
    return _parse_fast(header, text, numeric, textual) or parse_careful(
        header, text, numeric, textual, set(blank_is_nan)
    )


def parse_table(path: Path, header: list[str], text: str, numeric, textual=(), blank_is_nan=()) -> Table:
    table = parse_rows(header, text, numeric, textual, blank_is_nan)
    if len(table) == 0:
        raise CalibError(f"{path}: no sample rows; expected a header row and at least one sample row")
    return table


def flag_non_finite(table: Table, columns) -> None:
    for name in columns:
        values = table.numbers[name]
        table.flag(
            ~np.isfinite(values),
            lambda k, name=name, values=values: f"column '{name}': expected a finite number, got {float(values[k])!r}",
        )


def refuse_first(path: Path, table: Table) -> None:
    if table.issues:
        k = min(table.issues)
        raise CalibError(f"{path}: row {table.lines[k]}: {table.issues[k]}")
