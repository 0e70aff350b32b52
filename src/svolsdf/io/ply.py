"""PLY (and OBJ) reading and writing for point clouds and triangle meshes.

Files are written atomically: the data go to a uniquely named temporary file in the same folder,
which then replaces ``path`` with :func:`os.replace`, so a killed run never leaves a half-written
file behind, and a failed write (a full disk) removes it and names ``path``.

Conventions: coordinates are float32 in the writer's world units (docs/architecture.md
"Conventions": DTU millimetres); colours are uchar RGB; binary little-endian PLY.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from svolsdf.errors import InputError, raise_if_interrupted

__all__ = ["atomic_path", "read_ply", "write_mesh_ply", "write_obj", "write_points_ply",
           "write_textured_obj"]


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a unique temporary path beside ``path``; on success move it onto ``path``
    atomically.

    On an exception the temporary file is removed and ``path`` is left untouched; an `OSError`
    (no space left, read-only) becomes an `InputError` naming ``path``.
    """
    import errno

    from svolsdf.io.runfolder import unique_temp

    path = Path(path)
    try:
        tmp = unique_temp(path)
    except OSError as e:
        raise InputError(f"{path}: cannot write it ({e.strerror or e})") from None
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        why = "the disk is full" if e.errno == errno.ENOSPC else (e.strerror or str(e))
        raise InputError(f"{path}: cannot write it ({why})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _as_array(name: str, a, cols: int = 3) -> np.ndarray:
    a = np.asarray(a.detach().cpu() if hasattr(a, "detach") else a)
    if a.ndim != 2 or a.shape[1] != cols:
        raise ValueError(f"{name} must be (N, {cols}), got {a.shape}")
    return a


def _colors_u8(colors, n: int, name: str = "colors") -> np.ndarray:
    """(N, 3) uint8 from uint8 or float in [0, 1] colours."""
    c = _as_array(name, colors)
    if c.shape[0] != n:
        raise ValueError(f"{name} has {c.shape[0]} rows but there are {n} points")
    if c.dtype == np.uint8:
        return c
    if np.issubdtype(c.dtype, np.integer):
        return np.clip(c, 0, 255).astype(np.uint8)
    return np.clip(np.round(c.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


def _vertex_element(xyz, rgb=None, normals=None) -> PlyElement:
    xyz = _as_array("xyz", xyz)
    n = xyz.shape[0]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    if normals is not None:
        nrm = _as_array("normals", normals)
        if nrm.shape[0] != n:
            raise ValueError(f"normals has {nrm.shape[0]} rows but there are {n} points")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        cols.update(nx=nrm[:, 0], ny=nrm[:, 1], nz=nrm[:, 2])
    if rgb is not None:
        c = _colors_u8(rgb, n)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        cols.update(red=c[:, 0], green=c[:, 1], blue=c[:, 2])
    data = np.empty(n, dtype=fields)
    for k, v in cols.items():
        data[k] = v
    return PlyElement.describe(data, "vertex")


def write_points_ply(path, xyz, rgb=None, normals=None) -> Path:
    """Write a point cloud as binary little-endian PLY (float xyz and normals, uchar rgb).

    Args:
        path: output file (its folder must exist).
        xyz: (N, 3) points (numpy or torch, any float dtype; stored as float32).
        rgb: (N, 3) colours, uint8 or float in [0, 1], or None.
        normals: (N, 3) normals or None.

    Returns:
        The written path.
    """
    path = Path(path)
    el = _vertex_element(xyz, rgb, normals)
    with atomic_path(path) as tmp:
        PlyData([el], text=False, byte_order="<").write(str(tmp))
    return path


def write_mesh_ply(path, vertices, faces, vertex_colors=None) -> Path:
    """Write a triangle mesh as binary little-endian PLY.

    Args:
        path: output file.
        vertices: (V, 3) float positions.
        faces: (F, 3) integer vertex indices (stored as int32 ``vertex_indices`` lists).
        vertex_colors: (V, 3) uint8 or float in [0, 1], or None.

    Returns:
        The written path.
    """
    path = Path(path)
    v_el = _vertex_element(vertices, vertex_colors)
    f = _as_array("faces", faces).astype(np.int64)
    nv = len(v_el.data)
    if f.size and (f.min() < 0 or f.max() >= nv):
        raise ValueError(f"faces index vertices outside [0, {nv})")
    # Written by hand: plyfile serializes list properties row by row in Python (slow).
    vdata = v_el.data
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {nv}"]
    ply_type = {"f4": "float", "u1": "uchar"}
    for name in vdata.dtype.names:
        header.append(f"property {ply_type[vdata.dtype[name].str[1:]]} {name}")
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    frec = np.empty(len(f), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    frec["n"] = 3
    frec["v"] = f.astype(np.int32)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vdata.astype(vdata.dtype.newbyteorder("<")).tobytes())
        fh.write(frec.tobytes())
    return path


def write_obj(path, vertices, faces, vertex_colors=None) -> Path:
    """Write a triangle mesh as Wavefront OBJ (1-based indices; colours as ``v x y z r g b``).

    Args:
        path: output file.
        vertices: (V, 3) float positions.
        faces: (F, 3) integer 0-based vertex indices.
        vertex_colors: (V, 3) uint8 or float in [0, 1], or None.
    """
    path = Path(path)
    v = _as_array("vertices", vertices).astype(np.float64)
    f = _as_array("faces", faces).astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside [0, {len(v)})")
    lines = []
    if vertex_colors is not None:
        c = _colors_u8(vertex_colors, len(v), "vertex_colors").astype(np.float64) / 255.0
        lines += [f"v {a:.6f} {b:.6f} {d:.6f} {r:.4f} {g:.4f} {bb:.4f}"
                  for (a, b, d), (r, g, bb) in zip(v, c, strict=True)]
    else:
        lines += [f"v {a:.6f} {b:.6f} {d:.6f}" for a, b, d in v]
    lines += [f"f {i + 1} {j + 1} {k + 1}" for i, j, k in f]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def write_textured_obj(path, vertices, faces, uv, texture) -> list[Path]:
    """Write a mesh with a texture as Wavefront OBJ: ``path`` (.obj), its material
    (``path`` with .mtl) and the texture (.png) beside it, each atomically.

    Args:
        path: the .obj file.
        vertices: (V, 3) float positions; faces: (F, 3) 0-based vertex indices.
        uv: (F, 3, 2) texture coordinates of each face's corners (OBJ's: v up from the
            image's bottom row).
        texture: (H, W, 3) uint8 image.

    Returns:
        the three written paths.
    """
    from svolsdf.io.images import write_image

    path = Path(path)
    v = _as_array("vertices", vertices).astype(np.float64)
    f = _as_array("faces", faces).astype(np.int64)
    t = np.asarray(uv, np.float64)
    if t.shape != (len(f), 3, 2):
        raise ValueError(f"uv must be ({len(f)}, 3, 2), got {t.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside [0, {len(v)})")
    mtl, png = path.with_suffix(".mtl"), path.with_suffix(".png")
    fi = np.concatenate([f + 1, np.arange(1, 3 * len(f) + 1).reshape(-1, 3)], 1)
    lines = [f"mtllib {mtl.name}"]
    lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in v]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in t.reshape(-1, 2)]
    lines += ["usemtl atlas"]
    lines += [f"f {a}/{d} {b}/{e} {c}/{g}" for a, b, c, d, e, g in fi]
    write_image(png, np.ascontiguousarray(np.asarray(texture, np.uint8).transpose(2, 0, 1)))
    with atomic_path(mtl) as tmp:
        tmp.write_text(f"newmtl atlas\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
                       f"map_Kd {png.name}\n")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return [path, mtl, png]


def _read_plydata(path: Path) -> PlyData:
    """PlyData of ``path``; triangle faces are parsed as fixed-length lists (one numpy read
    instead of a Python loop per face: ~100x faster on a million faces) when every face is a
    triangle, else as variable-length lists."""
    for key in ("vertex_indices", "vertex_index"):
        try:
            ply = PlyData.read(str(path), known_list_len={"face": {key: 3}})
        except Exception:  # not all triangles, another property name, an ASCII file, ...
            raise_if_interrupted()
            continue
        if "face" not in [el.name for el in ply.elements] or key in (
                ply["face"].data.dtype.names or ()):
            return ply
    return PlyData.read(str(path))


def read_ply(path) -> dict:
    """Read a PLY point cloud or mesh (ASCII or binary).

    Args:
        path: a ``.ply`` file.

    Returns:
        dict with ``points`` (N, 3) float64, ``colors`` (N, 3) uint8 or None, ``normals`` (N, 3)
        float64 or None, ``faces`` (F, 3) int64 or None (polygons with more than 3 vertices are
        fan-triangulated).

    Raises:
        InputError: naming the file, if it is missing, not a PLY, or has no x/y/z vertex data.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: PLY file not found")
    try:
        ply = _read_plydata(path)
    except Exception as e:  # plyfile raises several types on malformed files
        raise InputError(f"{path}: not a readable PLY file ({type(e).__name__}: {e})") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise InputError(f"{path}: PLY file has no 'vertex' element (found {names})")
    v = ply["vertex"].data
    props = v.dtype.names or ()
    if not all(k in props for k in ("x", "y", "z")):
        raise InputError(f"{path}: PLY vertices lack x/y/z properties (found {list(props)})")
    points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    colors = None
    for keys in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green",
                                                             "diffuse_blue")):
        if all(k in props for k in keys):
            c = np.stack([v[k] for k in keys], axis=1)
            if np.issubdtype(c.dtype, np.floating):
                c = np.clip(np.round(c * 255.0), 0, 255)
            colors = c.astype(np.uint8)
            break
    normals = None
    if all(k in props for k in ("nx", "ny", "nz")):
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float64)
    faces = None
    if "face" in names:
        fd = ply["face"].data
        key = next((k for k in ("vertex_indices", "vertex_index") if k in (fd.dtype.names or ())),
                   None)
        if key is None:
            raise InputError(f"{path}: PLY faces lack 'vertex_indices'")
        polys = fd[key]
        if isinstance(polys, np.ndarray) and polys.ndim == 2 and polys.shape[1] == 3:
            faces = polys.astype(np.int64)  # read as fixed-length triangles (fast path)
        elif {len(p) for p in polys} <= {3}:  # triangles only
            faces = np.asarray(np.stack(list(polys)) if len(polys) else np.zeros((0, 3)),
                               dtype=np.int64).reshape(-1, 3)
        else:
            tris = []
            for poly in polys:
                poly = np.asarray(poly, dtype=np.int64)
                tris += [(poly[0], poly[i], poly[i + 1]) for i in range(1, len(poly) - 1)]
            faces = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        if faces.size and (faces.min() < 0 or faces.max() >= len(points)):
            raise InputError(f"{path}: PLY faces index vertices outside [0, {len(points)})")
    return {"points": points, "colors": colors, "normals": normals, "faces": faces}
