"""LAS and LAZ point clouds (the ASPRS format of laser scanners, survey tools and many phone-LiDAR exporters), read
and written with `laspy` (LAZ through its `lazrs` backend).

Read: the scaled coordinates, colour (16-bit channels brought to 8 bits; 8-bit values written by some tools kept
as they are), instance labels from an extra dimension ``instance`` or ``label`` (0 = unlabelled), normals from
extra dimensions ``normal_x/y/z`` when all three are there. Categories and provenance live in two variable-length
records of user id ``efem-viz`` (JSON). The point count the header declares is checked against `max_points` and
against the bytes the file holds (exactly for LAS, at most `_LAZ_POINTS_PER_BYTE` a byte for LAZ) before anything
is read.

Georeferenced files (coordinates beyond ±10 km, e.g. UTM) cannot be held in float32 to the millimetre: their
whole-metre minimum corner is subtracted and recorded as ``provenance["file_origin"]``; `data.scan.import_scan`
folds it into the scan frame, so outputs written with ``--frame original`` are in the file's coordinates again.

Write: LAS 1.4, point format 7 (coordinates, 16-bit colour), scale 0.1 µm for scans up to 200 m across (coarser
beyond), offsets at the minimum corner, labels and normals as extra dimensions; ``.laz`` compressed.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.formats.common import parse_categories
from efem_viz.data.scene import LIMIT_FLAG_HINT, Scene, SceneError

VLR_USER = "efem-viz"
"""User id of the variable-length records holding categories (record 1) and provenance (record 2)."""
_CATEGORIES_RECORD, _PROVENANCE_RECORD = 1, 2
GEOREFERENCED_M = 1e4
"""Coordinates beyond this (in file units) are shifted by their whole-unit minimum corner (float32 keeps ~1 mm
there)."""
_LAZ_POINTS_PER_BYTE = 64
"""A LAZ file declaring more points than this per byte it holds is damaged (LAZ keeps a point in several bytes)."""
_LABEL_DIMS = ("instance", "label")
_NORMAL_DIMS = ("normal_x", "normal_y", "normal_z")


def _laspy() -> Any:
    try:
        import laspy
    except ImportError:  # pragma: no cover - a dependency of the package
        raise SceneError("reading LAS/LAZ needs the laspy package (pip install laspy lazrs)") from None
    return laspy


def _check_header(p: Path, max_points: int) -> None:
    """The public header block's counts and offsets checked against the file's size before laspy reads it (a
    damaged header could otherwise make it loop over billions of records).

    Raises:
        SceneError: not LAS, an unknown version, counts or offsets the file cannot hold.
    """
    import struct

    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(375)
    if len(head) < 227 or head[:4] != b"LASF":
        raise SceneError("not a readable LAS/LAZ file (no LASF header)")
    major, minor = head[24], head[25]
    if major != 1 or minor > 4:
        raise SceneError(f"not a readable LAS/LAZ file (version {major}.{minor}; 1.0-1.4 are read)")
    header_size, data_offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    fmt, rec_len, legacy = struct.unpack_from("<BHI", head, 104)
    scales = struct.unpack_from("<3d", head, 131)
    offsets = struct.unpack_from("<3d", head, 155)
    if not 227 <= header_size <= data_offset <= size:
        raise SceneError(f"LAS header damaged: header size {header_size}, point data at byte {data_offset}, "
                         f"file of {size:,} bytes")
    if n_vlrs * 54 > data_offset - header_size:
        raise SceneError(f"LAS header damaged: {n_vlrs:,} variable-length records cannot fit before byte {data_offset}")
    if (fmt & 0x3F) > 10 or not 20 <= rec_len <= 1024:
        raise SceneError(f"LAS header damaged: point format {fmt & 0x3F}, record length {rec_len}")
    if not all(np.isfinite(v) for v in (*scales, *offsets)) or any(v == 0.0 for v in scales):
        raise SceneError("LAS header damaged: scale or offset not finite, or a zero scale")
    n = legacy
    if minor >= 4:
        if len(head) < 375:
            raise SceneError("LAS 1.4 header truncated")
        evlr_start, n_evlrs, n64 = struct.unpack_from("<QIQ", head, 235)
        if n_evlrs and (evlr_start > size or n_evlrs * 60 > size - min(evlr_start, size)):
            raise SceneError(f"LAS header damaged: {n_evlrs:,} extended records at byte {evlr_start:,} of {size:,}")
        n = n64 or legacy
    if n > max_points:
        raise SceneError(f"LAS header declares {n:,} points, more than the limit {max_points:,} ({LIMIT_FLAG_HINT})")


def load(p: Path, max_points: int) -> dict[str, Any]:
    """The `Scene.create` arguments of a LAS or LAZ file (see the module docstring)."""
    laspy = _laspy()
    _check_header(p, max_points)
    try:
        reader = laspy.open(str(p))
    except Exception as exc:  # noqa: BLE001 - laspy raises its own and OS errors for a damaged header
        raise SceneError(f"not a readable LAS/LAZ file ({type(exc).__name__}: {str(exc)[:160]})") from None
    with reader:
        header = reader.header
        n = int(header.point_count)
        if n <= 0:
            raise SceneError("LAS file holds no points")
        if n > max_points:
            raise SceneError(f"LAS header declares {n:,} points, more than the limit {max_points:,} "
                             f"({LIMIT_FLAG_HINT})")
        if header.are_points_compressed and n > _LAZ_POINTS_PER_BYTE * p.stat().st_size:
            raise SceneError(f"LAZ header declares {n:,} points in a file of {p.stat().st_size:,} bytes: more than "
                             f"{_LAZ_POINTS_PER_BYTE} a byte, a damaged header")
        if not header.are_points_compressed:
            need = int(header.offset_to_point_data) + n * int(header.point_format.size)
            have = p.stat().st_size
            if need > have:
                raise SceneError(f"LAS file truncated: the header declares {n:,} points ({need:,} bytes), the file "
                                 f"has {have:,} bytes")
        try:
            las = reader.read()
        except Exception as exc:  # noqa: BLE001 - a damaged body (LAZ chunks, short reads)
            raise SceneError(f"LAS/LAZ body unreadable ({type(exc).__name__}: {str(exc)[:160]})") from None
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
    if len(xyz) != n:
        raise SceneError(f"LAS file holds {len(xyz):,} points, its header declares {n:,}")
    if not np.isfinite(xyz).all():
        raise SceneError("LAS file holds NaN or infinite coordinates (a damaged scale or offset)")
    out: dict[str, Any] = {}
    prov: dict[str, Any] = {}
    cats: dict[int, str] | None = None
    for vlr in las.vlrs:
        if getattr(vlr, "user_id", "") != VLR_USER:
            continue
        text = bytes(getattr(vlr, "record_data", b"")).decode("utf-8", errors="replace")
        if vlr.record_id == _CATEGORIES_RECORD:
            cats = parse_categories(text)
        elif vlr.record_id == _PROVENANCE_RECORD:
            rec = json.loads(text)
            if not isinstance(rec, dict):
                raise SceneError("LAS provenance record is not a JSON object")
            prov = rec
    if np.abs(xyz).max() > GEOREFERENCED_M:
        origin = np.floor(xyz.min(axis=0))
        xyz = xyz - origin
        prov = {**prov, "file_origin": origin.tolist()}
    out["points"] = xyz
    dims = set(las.point_format.dimension_names)
    if {"red", "green", "blue"} <= dims:
        rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], axis=1).astype(np.int64)
        out["colors"] = (rgb if rgb.max(initial=0) <= 255 else rgb >> 8).astype(np.uint8)
    if set(_NORMAL_DIMS) <= dims:
        nrm = np.stack([np.asarray(las[d]) for d in _NORMAL_DIMS], axis=1).astype(np.float64)
        if np.isfinite(nrm).all() and (np.linalg.norm(nrm, axis=1) > 0).all():
            out["normals"] = nrm
    for dim in _LABEL_DIMS:
        if dim in dims:
            lab = np.asarray(las[dim])
            if lab.dtype.kind == "f" and not (np.isfinite(lab).all() and (lab == np.round(lab)).all()):
                raise SceneError(f"LAS dimension {dim!r} holds non-integer instance labels")
            out["instance"] = lab.astype(np.int64)
            break
    if cats is not None:
        out["categories"] = cats
    if prov:
        out["provenance"] = prov
    return out


def save(scene: Scene, tmp: Path, *, ascii: bool = False, compress: bool = False) -> None:
    """Write LAS 1.4 (point format 7; see the module docstring); ``compress``: LAZ. ``ascii`` has no meaning here.
    Meshes are written as their vertices (LAS has no faces)."""
    laspy = _laspy()
    header = laspy.LasHeader(point_format=7, version="1.4")
    pts = scene.points.astype(np.float64)
    lo = np.floor(pts.min(axis=0)) if len(pts) else np.zeros(3)
    extent = float((pts.max(axis=0) - lo).max()) if len(pts) else 1.0
    scale = 1e-7 if extent < 200.0 else 10.0 ** np.ceil(np.log10(extent / 2e9))
    header.offsets = lo
    header.scales = np.full(3, scale)
    if scene.instance is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="instance", type=np.int32))
    if not scene.normals_pending:
        for d in _NORMAL_DIMS:
            header.add_extra_dim(laspy.ExtraBytesParams(name=d, type=np.float32))
    if scene.categories:
        header.vlrs.append(laspy.VLR(user_id=VLR_USER, record_id=_CATEGORIES_RECORD, description="categories",
                                     record_data=json.dumps({str(k): v for k, v in scene.categories.items()}).encode()))
    if scene.provenance:
        header.vlrs.append(laspy.VLR(user_id=VLR_USER, record_id=_PROVENANCE_RECORD, description="provenance",
                                     record_data=json.dumps(dict(scene.provenance), default=str).encode()))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    rgb = scene.colors.astype(np.uint16) * np.uint16(257)  # 8 -> 16 bits, 255 -> 65535
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if scene.instance is not None:
        las.instance = np.asarray(scene.instance, np.int32)
    if not scene.normals_pending:
        nrm = scene.normals
        for i, d in enumerate(_NORMAL_DIMS):
            las[d] = nrm[:, i].astype(np.float32)
    with open(tmp, "wb") as fh:
        las.write(fh, do_compress=compress)


def save_laz(scene: Scene, tmp: Path, *, ascii: bool = False) -> None:
    """`save`, compressed (LAZ)."""
    save(scene, tmp, ascii=ascii, compress=True)
