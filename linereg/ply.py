"""PLY files: an ascii or binary reader that checks the header line by line and the data against the
counts it declares (a truncated, padded or malformed file is an error naming the reason), and a
binary writer (:mod:`linereg.io` reads and writes point clouds through them).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np


class _PlyProperty(NamedTuple):
    """One ``property`` line: its name, numpy value type and, for a list, the count type."""

    name: str
    dtype: str
    count_dtype: str | None


class _PlyElement(NamedTuple):
    """One ``element`` line and the properties that follow it."""

    name: str
    count: int
    properties: list[_PlyProperty]


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (and normals) of an ascii or binary PLY file, whose header and data length are
    checked against each other (a truncated or padded file is an error)."""
    with path.open("rb") as stream:
        byte_order, elements = _read_ply_header(stream)
        body = stream.read()
    vertex = next((element for element in elements if element.name == "vertex"), None)
    if vertex is None:
        raise ValueError(f"no 'vertex' element in the PLY header (elements: {[e.name for e in elements]})")
    names = [prop.name for prop in vertex.properties]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise ValueError(
            f"the vertex element lacks the propert{'ies' if len(missing) > 1 else 'y'} {missing} (it has {names})"
        )
    if any(prop.count_dtype is not None for prop in vertex.properties):
        raise ValueError(f"list properties in the vertex element are not supported (properties {names})")
    reader = _ply_ascii_vertices if byte_order is None else _ply_binary_vertices
    data = reader(body, elements, vertex, byte_order or "")
    xyz = np.column_stack([data[axis].astype(np.float32) for axis in "xyz"]).reshape(-1, 3)
    normals = None
    if {"nx", "ny", "nz"} <= set(names):
        normals = np.column_stack([data[axis].astype(np.float32) for axis in ("nx", "ny", "nz")]).reshape(-1, 3)
    return xyz, normals


_PLY_TYPES = {
    **dict.fromkeys(("char", "int8"), "i1"),
    **dict.fromkeys(("uchar", "uint8"), "u1"),
    **dict.fromkeys(("short", "int16"), "i2"),
    **dict.fromkeys(("ushort", "uint16"), "u2"),
    **dict.fromkeys(("int", "int32"), "i4"),
    **dict.fromkeys(("uint", "uint32"), "u4"),
    **dict.fromkeys(("float", "float32"), "f4"),
    **dict.fromkeys(("double", "float64"), "f8"),
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def _read_ply_header(stream) -> tuple[str | None, list[_PlyElement]]:
    """Parse a PLY header up to ``end_header``; returns the byte order (``None``: ascii) and elements."""
    first = stream.readline()
    if not first:
        raise ValueError("the file is empty")
    if first.rstrip(b"\r\n") != b"ply":
        raise ValueError("not a PLY file (its first line is not 'ply')")
    byte_order: str | None = None
    known_format = False
    elements: list[_PlyElement] = []
    number = 1
    while True:
        raw = stream.readline()
        number += 1
        if not raw:
            raise ValueError("the PLY header has no 'end_header' line")
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword, arguments = words[0], words[1:]
        if keyword == "end_header":
            break
        if keyword == "format":
            if not arguments or arguments[0] not in _PLY_FORMATS:
                raise ValueError(
                    f"header line {number}: unknown PLY format {' '.join(arguments)!r}; expected one of "
                    f"{', '.join(_PLY_FORMATS)}"
                )
            byte_order, known_format = _PLY_FORMATS[arguments[0]], True
        elif keyword == "element":
            if len(arguments) != 2 or not arguments[1].isdigit():
                raise ValueError(f"header line {number}: expected 'element <name> <count>', got {' '.join(words)!r}")
            elements.append(_PlyElement(arguments[0], int(arguments[1]), []))
        elif keyword == "property":
            if not elements:
                raise ValueError(f"header line {number}: a property before any element")
            elements[-1].properties.append(_ply_property(arguments, number))
        else:
            raise ValueError(
                f"header line {number}: {raw.decode('ascii', errors='replace').strip()[:40]!r} is not a PLY header "
                "line (a missing 'end_header' line?)"
            )
    if not known_format:
        raise ValueError("the PLY header has no 'format' line")
    return byte_order, elements


def _ply_property(arguments: list[str], number: int) -> _PlyProperty:
    """A ``property <type> <name>`` or ``property list <count type> <type> <name>`` line."""
    is_list = bool(arguments) and arguments[0] == "list"
    types = arguments[1:3] if is_list else arguments[:1]
    if len(arguments) != (4 if is_list else 2) or any(kind not in _PLY_TYPES for kind in types):
        raise ValueError(
            f"header line {number}: bad property {' '.join(arguments)!r}; expected 'property <type> <name>' or "
            f"'property list <type> <type> <name>' with types {', '.join(sorted(_PLY_TYPES))}"
        )
    if is_list:
        return _PlyProperty(arguments[3], _PLY_TYPES[types[1]], _PLY_TYPES[types[0]])
    return _PlyProperty(arguments[1], _PLY_TYPES[types[0]], None)


def _ply_ascii_vertices(body: bytes, elements: list[_PlyElement], vertex: _PlyElement, _: str) -> dict:
    """The vertex columns of an ascii PLY body (one element instance per non-blank line)."""
    lines = [line for line in body.decode("ascii", errors="replace").splitlines() if line.strip()]
    declared = sum(element.count for element in elements)
    if len(lines) != declared:
        counts = ", ".join(f"{element.name}: {element.count}" for element in elements)
        problem = "truncated" if len(lines) < declared else "more data than the header declares"
        raise ValueError(
            f"the header declares {counts} ({declared} data lines) but the file holds {len(lines)}: {problem}"
        )
    start = sum(element.count for element in elements[: elements.index(vertex)])
    rows = [line.split() for line in lines[start : start + vertex.count]]
    width = len(vertex.properties)
    for offset, row in enumerate(rows):
        if len(row) != width:
            raise ValueError(f"vertex {offset} has {len(row)} values, the header declares {width} properties")
    values = np.array(rows, dtype=np.float64).reshape(vertex.count, width)
    return {prop.name: values[:, column] for column, prop in enumerate(vertex.properties)}


def _ply_binary_vertices(body: bytes, elements: list[_PlyElement], vertex: _PlyElement, byte_order: str) -> dict:
    """The vertex columns of a binary PLY body; the elements before it are skipped."""
    offset = 0
    for element in elements[: elements.index(vertex)]:
        offset = _skip_ply_element(body, offset, element, byte_order)
    dtype = np.dtype([(prop.name, byte_order + prop.dtype) for prop in vertex.properties])
    needed = vertex.count * dtype.itemsize
    rest = elements[elements.index(vertex) + 1 :]
    needed_after = sum(
        element.count * sum(np.dtype(prop.count_dtype or prop.dtype).itemsize for prop in element.properties)
        for element in rest
    )
    if len(body) - offset < needed + needed_after:
        raise ValueError(
            f"truncated: the header declares {vertex.count} vertices of {dtype.itemsize} bytes"
            f"{' and further elements' if rest else ''} (at least {offset + needed + needed_after} bytes of data) "
            f"but the file holds {len(body)} bytes after the header"
        )
    return np.frombuffer(body, dtype=dtype, count=vertex.count, offset=offset)


def _skip_ply_element(body: bytes, offset: int, element: _PlyElement, byte_order: str) -> int:
    """The offset just after ``element`` in a binary PLY body starting at ``offset``."""
    for _ in range(element.count):
        for prop in element.properties:
            if prop.count_dtype is None:
                offset += np.dtype(prop.dtype).itemsize
                continue
            count_type = np.dtype(byte_order + prop.count_dtype)
            if offset + count_type.itemsize > len(body):
                raise ValueError(f"truncated inside the {element.name!r} element")
            length = int(np.frombuffer(body, dtype=count_type, count=1, offset=offset)[0])
            offset += count_type.itemsize + length * np.dtype(prop.dtype).itemsize
    if offset > len(body):
        raise ValueError(f"truncated inside the {element.name!r} element")
    return offset


def write_ply(path: Path, columns: np.ndarray) -> None:
    """Binary little-endian PLY with float32 ``x y z [nx ny nz]`` vertex properties."""
    names = ("x", "y", "z", "nx", "ny", "nz")[: columns.shape[1]]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {columns.shape[0]}",
        *(f"property float {name}" for name in names),
        "end_header",
    ]
    write_binary(path, header, columns)


def write_binary(path: Path, header: list[str], columns: np.ndarray) -> None:
    """``header`` (ASCII lines) followed by ``columns (N, C)`` as little-endian float32 rows: the
    body of a binary PLY or PCD file."""
    with path.open("wb") as stream:
        stream.write(("\n".join(header) + "\n").encode("ascii"))
        stream.write(columns.astype("<f4").tobytes())
