"""COLMAP sparse models: read and write (text and binary), and load a COLMAP scene folder.

Layout (what COLMAP, nerfstudio's ``ns-process-data`` and ``warpnerf process`` produce)::

    <scene>/images/...                          # the photos, names as in images.txt/bin
    <scene>/sparse/0/cameras.{txt,bin}          # also <scene>/sparse/ or <scene>/colmap/sparse/0/
    <scene>/sparse/0/images.{txt,bin}
    <scene>/sparse/0/points3D.{txt,bin}         # optional: bounds then come from the cameras
    <scene>/{train,val,test}_list.txt           # optional: one image name a line; else every 8th is test

The file format is COLMAP's documented one (https://colmap.github.io/format.html), read and
written here in plain Python (no dependency; pycolmap reads what :func:`write_model` writes, which
the tests check). Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; images of
distorted or differing cameras are resampled to one pinhole camera at load time
(:mod:`warpnerf.data.distortion`). Poses are world-to-camera (quaternion w, x, y, z and translation)
in OpenCV axes (x right, y down, z forward) and become OpenGL camera-to-world matrices, then the
world is normalised as documented in :mod:`warpnerf.data.normalize`: a model without points from an
object rig is centred on the point its cameras look at (:func:`warpnerf.data.capture.build_scene`).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field

import numpy as np

from warpnerf.data.capture import Frame, build_scene
from warpnerf.data.distortion import Intrinsics
from warpnerf.data.errors import DatasetError
from warpnerf.data.scene import Scene

# name -> (COLMAP model id, number of parameters); every model COLMAP defines, so binary files of
# any model parse, and unsupported ones get a clear error instead of garbage.
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": (0, 3),
    "PINHOLE": (1, 4),
    "SIMPLE_RADIAL": (2, 4),
    "RADIAL": (3, 5),
    "OPENCV": (4, 8),
    "OPENCV_FISHEYE": (5, 8),
    "FULL_OPENCV": (6, 12),
    "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4),
    "RADIAL_FISHEYE": (9, 5),
    "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
}
MODEL_BY_ID = {mid: name for name, (mid, _) in CAMERA_MODELS.items()}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class Camera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # float64, COLMAP's parameter order for the model


@dataclass
class Image:
    id: int
    qvec: np.ndarray  # (4,) w, x, y, z: world-to-camera rotation
    tvec: np.ndarray  # (3,) world-to-camera translation
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K, 2) observed keypoints, pixels
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) -1 = none


@dataclass
class Point3D:
    id: int
    xyz: np.ndarray  # (3,)
    rgb: np.ndarray  # (3,) uint8
    error: float
    image_ids: np.ndarray  # (L,) int
    point2D_idxs: np.ndarray  # (L,) int


# ---- camera models <-> intrinsics -------------------------------------------------------------


def camera_intrinsics(cam: Camera, source: str) -> Intrinsics:
    """COLMAP camera -> :class:`Intrinsics`; DatasetError for models warpnerf cannot use."""
    p = [float(x) for x in cam.params]
    m = cam.model
    if m == "SIMPLE_PINHOLE":
        return Intrinsics(cam.width, cam.height, p[0], p[0], p[1], p[2])
    if m == "PINHOLE":
        return Intrinsics(cam.width, cam.height, p[0], p[1], p[2], p[3])
    if m == "SIMPLE_RADIAL":
        return Intrinsics(cam.width, cam.height, p[0], p[0], p[1], p[2], k1=p[3])
    if m == "RADIAL":
        return Intrinsics(cam.width, cam.height, p[0], p[0], p[1], p[2], k1=p[3], k2=p[4])
    if m == "OPENCV":
        return Intrinsics(cam.width, cam.height, p[0], p[1], p[2], p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    raise DatasetError(
        f"{source}: camera {cam.id} uses the {m} model, which warpnerf does not support "
        f"(supported: {', '.join(SUPPORTED_MODELS)}; undistort with 'colmap image_undistorter' first)"
    )


def intrinsics_camera(cam_id: int, k: Intrinsics) -> Camera:
    """The simplest COLMAP camera model that holds ``k`` exactly."""
    if k.k3 != 0.0:
        raise ValueError("COLMAP's OPENCV model has no k3 coefficient")
    if not k.distorted:
        if k.fx == k.fy:
            return Camera(cam_id, "SIMPLE_PINHOLE", k.width, k.height, np.array([k.fx, k.cx, k.cy]))
        return Camera(cam_id, "PINHOLE", k.width, k.height, np.array([k.fx, k.fy, k.cx, k.cy]))
    if k.fx == k.fy and k.p1 == 0.0 and k.p2 == 0.0:
        if k.k2 == 0.0:
            return Camera(cam_id, "SIMPLE_RADIAL", k.width, k.height, np.array([k.fx, k.cx, k.cy, k.k1]))
        return Camera(cam_id, "RADIAL", k.width, k.height, np.array([k.fx, k.cx, k.cy, k.k1, k.k2]))
    return Camera(cam_id, "OPENCV", k.width, k.height, np.array([k.fx, k.fy, k.cx, k.cy, k.k1, k.k2, k.p1, k.p2]))


# ---- poses ------------------------------------------------------------------------------------


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_qvec(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> unit quaternion (w, x, y, z) with w >= 0 (the eigenvector method, robust)."""
    r = np.asarray(r, np.float64)
    rxx, ryx, rzx, rxy, ryy, rzy, rxz, ryz, rzz = r.flat
    k = np.array([
        [rxx - ryy - rzz, 0, 0, 0],
        [ryx + rxy, ryy - rxx - rzz, 0, 0],
        [rzx + rxz, rzy + ryz, rzz - rxx - ryy, 0],
        [ryz - rzy, rzx - rxz, rxy - ryx, rxx + ryy + rzz],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(k)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


_CV_TO_GL = np.diag([1.0, -1.0, -1.0])  # flips camera y (down -> up) and z (forward -> back)


def image_c2w(img: Image) -> np.ndarray:
    """(3, 4) OpenGL camera-to-world of a COLMAP image (world-to-camera, OpenCV axes)."""
    r = qvec_to_rotmat(img.qvec)
    t = np.asarray(img.tvec, np.float64)
    return np.concatenate([r.T @ _CV_TO_GL, (-r.T @ t)[:, None]], axis=1)


def c2w_to_colmap(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3, 4) OpenGL camera-to-world -> (qvec, tvec) world-to-camera in OpenCV axes."""
    c2w = np.asarray(c2w, np.float64)
    r = (c2w[:, :3] @ _CV_TO_GL).T
    return rotmat_to_qvec(r), -r @ c2w[:, 3]


# ---- reading ------------------------------------------------------------------------------------


def _text_lines(path: str) -> list[str]:
    """Lines of a COLMAP text file without comments; empty lines kept (an image without
    keypoints has an empty second line)."""
    try:
        with open(path, encoding="utf-8") as f:
            lines = [ln.rstrip("\r\n") for ln in f]
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from None
    return [ln for ln in lines if not ln.lstrip().startswith("#")]


def _bad(path: str, what: str) -> DatasetError:
    return DatasetError(f"malformed COLMAP file {path}: {what}")


def read_cameras_text(path: str) -> dict[int, Camera]:
    cams = {}
    for ln in _text_lines(path):
        parts = ln.split()
        if not parts:
            continue
        try:
            cid, model, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = np.array([float(x) for x in parts[4:]])
        except (ValueError, IndexError):
            raise _bad(path, f"cannot parse line '{ln.strip()}'") from None
        if model in CAMERA_MODELS and len(params) != CAMERA_MODELS[model][1]:
            raise _bad(path, f"camera {cid} ({model}) has {len(params)} parameters, expected {CAMERA_MODELS[model][1]}")
        cams[cid] = Camera(cid, model, w, h, params)
    return cams


def read_images_text(path: str) -> dict[int, Image]:
    lines = _text_lines(path)
    imgs, i = {}, 0
    while i < len(lines):
        parts = lines[i].split()
        if not parts:
            i += 1
            continue
        try:
            iid = int(parts[0])
            q = np.array([float(x) for x in parts[1:5]])
            t = np.array([float(x) for x in parts[5:8]])
            cid = int(parts[8])
            name = " ".join(parts[9:])  # names may hold spaces
        except (ValueError, IndexError):
            raise _bad(path, f"cannot parse image line '{lines[i].strip()}'") from None
        if len(q) != 4 or len(t) != 3 or not name:
            raise _bad(path, f"cannot parse image line '{lines[i].strip()}'")
        pts = lines[i + 1].split() if i + 1 < len(lines) else []
        try:
            arr = np.array([float(x) for x in pts]).reshape(-1, 3)
        except ValueError:
            raise _bad(path, f"keypoint line of image {iid} is not triples of numbers") from None
        imgs[iid] = Image(iid, q, t, cid, name, arr[:, :2], arr[:, 2].astype(np.int64))
        i += 2
    return imgs


def read_points3D_text(path: str) -> dict[int, Point3D]:
    pts = {}
    for ln in _text_lines(path):
        parts = ln.split()
        if not parts:
            continue
        try:
            pid = int(parts[0])
            xyz = np.array([float(x) for x in parts[1:4]])
            rgb = np.array([int(x) for x in parts[4:7]], np.uint8)
            err = float(parts[7])
            track = np.array([int(x) for x in parts[8:]], np.int64).reshape(-1, 2)
        except (ValueError, IndexError):
            raise _bad(path, f"cannot parse point line '{ln.strip()[:80]}'") from None
        pts[pid] = Point3D(pid, xyz, rgb, err, track[:, 0], track[:, 1])
    return pts


class _Reader:
    def __init__(self, path: str):
        self.path = path
        try:
            with open(path, "rb") as f:
                self.data = f.read()
        except OSError as exc:
            raise DatasetError(f"cannot read {path}: {exc}") from None
        self.pos = 0

    def read(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise _bad(self.path, "file ends early (truncated?)")
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return out

    def array(self, dtype, count: int) -> np.ndarray:
        dt = np.dtype(dtype)
        size = dt.itemsize * count
        if self.pos + size > len(self.data):
            raise _bad(self.path, "file ends early (truncated?)")
        out = np.frombuffer(self.data, dt, count, self.pos).copy()
        self.pos += size
        return out

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise _bad(self.path, "unterminated image name")
        s = self.data[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s


def read_cameras_binary(path: str) -> dict[int, Camera]:
    r = _Reader(path)
    cams = {}
    for _ in range(r.read("<Q")[0]):
        cid, mid, w, h = r.read("<iiQQ")
        if mid not in MODEL_BY_ID:
            raise _bad(path, f"camera {cid} has unknown model id {mid}")
        model = MODEL_BY_ID[mid]
        cams[cid] = Camera(cid, model, int(w), int(h), r.array("<f8", CAMERA_MODELS[model][1]))
    return cams


def read_images_binary(path: str) -> dict[int, Image]:
    r = _Reader(path)
    imgs = {}
    for _ in range(r.read("<Q")[0]):
        vals = r.read("<i7di")
        iid, q, t, cid = vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8]
        name = r.cstring()
        n = r.read("<Q")[0]
        rec = r.array([("x", "<f8"), ("y", "<f8"), ("id", "<i8")], n)
        imgs[iid] = Image(iid, q, t, cid, name, np.stack([rec["x"], rec["y"]], -1), rec["id"].astype(np.int64))
    return imgs


def read_points3D_binary(path: str) -> dict[int, Point3D]:
    r = _Reader(path)
    pts = {}
    for _ in range(r.read("<Q")[0]):
        vals = r.read("<Q3d3Bd")
        pid, xyz, rgb, err = vals[0], np.array(vals[1:4]), np.array(vals[4:7], np.uint8), vals[7]
        n = r.read("<Q")[0]
        track = r.array("<i4", 2 * n).reshape(-1, 2)
        pts[pid] = Point3D(pid, xyz, rgb, err, track[:, 0].astype(np.int64), track[:, 1].astype(np.int64))
    return pts


def model_format(folder: str) -> str | None:
    """".bin" or ".txt" when ``folder`` holds a complete COLMAP model (binary preferred), else None."""
    for ext in (".bin", ".txt"):
        if all(os.path.isfile(os.path.join(folder, f + ext)) for f in ("cameras", "images")):
            return ext
    return None


def read_model(folder: str, ext: str | None = None):
    """(cameras, images, points3D) dicts of the model in ``folder``; points3D may be empty."""
    ext = ext or model_format(folder)
    if ext is None:
        raise DatasetError(f"no COLMAP model in {folder} (need cameras.bin + images.bin or cameras.txt + images.txt)")
    readers = {
        ".txt": (read_cameras_text, read_images_text, read_points3D_text),
        ".bin": (read_cameras_binary, read_images_binary, read_points3D_binary),
    }[ext]
    cams = readers[0](os.path.join(folder, "cameras" + ext))
    imgs = readers[1](os.path.join(folder, "images" + ext))
    pts_path = os.path.join(folder, "points3D" + ext)
    pts = readers[2](pts_path) if os.path.isfile(pts_path) else {}
    return cams, imgs, pts


# ---- writing ------------------------------------------------------------------------------------


def write_model(folder: str, cameras: dict[int, Camera], images: dict[int, Image], points: dict[int, Point3D], ext: str = ".bin") -> None:
    """Write a COLMAP model (``ext`` ".bin" or ".txt") into ``folder`` (created)."""
    os.makedirs(folder, exist_ok=True)
    if ext == ".txt":
        _write_text(folder, cameras, images, points)
    elif ext == ".bin":
        _write_binary(folder, cameras, images, points)
    else:
        raise ValueError(f"ext must be '.bin' or '.txt', got {ext!r}")


def _fmt(x) -> str:
    return repr(float(x))  # shortest exact round trip of a float64


def _write_text(folder, cameras, images, points) -> None:
    with open(os.path.join(folder, "cameras.txt"), "w", encoding="utf-8") as f:
        f.write("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(cameras)}\n")
        for c in cameras.values():
            f.write(" ".join([str(c.id), c.model, str(c.width), str(c.height)] + [_fmt(p) for p in c.params]) + "\n")
    with open(os.path.join(folder, "images.txt"), "w", encoding="utf-8") as f:
        f.write("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {len(images)}\n")
        for im in images.values():
            f.write(" ".join([str(im.id)] + [_fmt(x) for x in im.qvec] + [_fmt(x) for x in im.tvec] + [str(im.camera_id), im.name]) + "\n")
            f.write(" ".join(f"{_fmt(x)} {_fmt(y)} {int(p)}" for (x, y), p in zip(im.xys, im.point3D_ids)) + "\n")
    with open(os.path.join(folder, "points3D.txt"), "w", encoding="utf-8") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {len(points)}\n")
        for p in points.values():
            track = " ".join(f"{int(a)} {int(b)}" for a, b in zip(p.image_ids, p.point2D_idxs))
            f.write(" ".join([str(p.id)] + [_fmt(x) for x in p.xyz] + [str(int(c)) for c in p.rgb] + [_fmt(p.error)]) + (" " + track if track else "") + "\n")


def _write_binary(folder, cameras, images, points) -> None:
    with open(os.path.join(folder, "cameras.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        for c in cameras.values():
            f.write(struct.pack("<iiQQ", c.id, CAMERA_MODELS[c.model][0], c.width, c.height))
            f.write(np.asarray(c.params, "<f8").tobytes())
    with open(os.path.join(folder, "images.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for im in images.values():
            f.write(struct.pack("<i7di", im.id, *[float(x) for x in im.qvec], *[float(x) for x in im.tvec], im.camera_id))
            f.write(im.name.encode("utf-8") + b"\0")
            f.write(struct.pack("<Q", len(im.point3D_ids)))
            rec = np.zeros(len(im.point3D_ids), [("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
            if len(rec):
                rec["x"], rec["y"], rec["id"] = im.xys[:, 0], im.xys[:, 1], im.point3D_ids
            f.write(rec.tobytes())
    with open(os.path.join(folder, "points3D.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for p in points.values():
            f.write(struct.pack("<Q3d3Bd", p.id, *[float(x) for x in p.xyz], *[int(c) for c in p.rgb], float(p.error)))
            f.write(struct.pack("<Q", len(p.image_ids)))
            f.write(np.stack([p.image_ids, p.point2D_idxs], -1).astype("<i4").tobytes())


# ---- loading a scene folder -------------------------------------------------------------------


SPARSE_DIRS = ("sparse/0", "sparse", "colmap/sparse/0", "colmap/sparse")
IMAGE_DIRS = ("images", "colmap/images")


def find_sparse(root: str) -> str | None:
    """The model folder of a COLMAP scene ``root`` (first of SPARSE_DIRS holding a model), or None."""
    for sub in SPARSE_DIRS:
        folder = os.path.join(root, sub)
        if model_format(folder):
            return folder
    return None


def read_split_lists(root: str) -> dict[str, list[str]] | None:
    """{split: names} from ``<root>/{train,val,test}_list.txt`` when ``train_list.txt`` exists."""
    if not os.path.isfile(os.path.join(root, "train_list.txt")):
        return None
    out = {}
    for split in ("train", "val", "test"):
        path = os.path.join(root, f"{split}_list.txt")
        if os.path.isfile(path):
            with open(path, encoding="utf-8") as f:
                out[split] = [ln.strip() for ln in f if ln.strip() and not ln.startswith("#")]
    return out


def read_colmap_poses(root: str) -> np.ndarray:
    """(N, 3, 4) OpenGL camera-to-world of the registered images of COLMAP scene ``root`` (sorted by name),
    read from the images file alone: what :func:`warpnerf.data.resolve.capture_rig` needs to classify the rig
    before anything loads. DatasetError when there is no model or no finite pose."""
    sparse = find_sparse(root)
    if sparse is None:
        raise DatasetError(f"no COLMAP sparse model in {root}")
    ext = model_format(sparse)
    path = os.path.join(sparse, "images" + ext)
    imgs = read_images_text(path) if ext == ".txt" else read_images_binary(path)
    poses = [image_c2w(im) for im in sorted(imgs.values(), key=lambda im: im.name)
             if np.all(np.isfinite(im.qvec)) and np.all(np.isfinite(im.tvec)) and np.linalg.norm(im.qvec) > 1e-12]
    if not poses:
        raise DatasetError(f"{path}: no registered image")
    return np.stack(poses)


def load_colmap(
    root: str,
    downscale: int = 1,
    holdout: int = 8,
    white_background: bool = True,
    images_dir: str | None = None,
    normalize: bool = True,
    name: str | None = None,
    unbounded: bool | None = None,
    ndc: bool | None = None,
    pixels: bool = True,
) -> Scene:
    """Load a COLMAP scene folder (module docstring) into a :class:`Scene` (kind "colmap").

    Args:
        root: scene folder.
        downscale: integer block-average downscale (after undistortion).
        holdout: every ``holdout``-th image (sorted by name) is a test view, unless
            ``train_list.txt`` names the split.
        white_background: composite RGBA photos on white (else black); the render background.
        images_dir: image folder (default ``images``, else ``colmap/images``).
        normalize: map the world as in :mod:`warpnerf.data.normalize` (``scene.normalization``, whose
            ``framing`` says which framing and ray space the rig got and why).
        unbounded, ndc: the ray space; None: chosen from the rig (forward-facing: NDC, 360°: contracted;
            :func:`warpnerf.data.capture.build_scene`).
        pixels: False: a cameras-only load (:func:`~warpnerf.data.capture.build_scene`).

    Raises:
        DatasetError naming the file: no model folder, unsupported camera model, missing image,
            non-finite pose, no registered image, malformed file.
    """
    if not os.path.isdir(root):
        raise DatasetError(f"scene folder not found: {root}")
    sparse = find_sparse(root)
    if sparse is None:
        raise DatasetError(
            f"no COLMAP sparse model in {root} (looked for cameras + images .bin/.txt in {', '.join(SPARSE_DIRS)}); "
            f"run 'warpnerf process --images DIR --out {root}' to make one"
        )
    ext = model_format(sparse)
    cams, imgs, pts = read_model(sparse, ext)
    images_path = os.path.join(sparse, "images" + ext)
    if not imgs:
        raise DatasetError(f"{images_path}: no registered image")
    if images_dir is None:
        images_dir = next((os.path.join(root, d) for d in IMAGE_DIRS if os.path.isdir(os.path.join(root, d))), None)
        if images_dir is None:
            raise DatasetError(f"image folder not found: {os.path.join(root, 'images')}")
    intr = {}
    frames = []
    for im in sorted(imgs.values(), key=lambda im: im.name):
        if im.camera_id not in cams:
            raise DatasetError(f"{images_path}: image {im.name} uses camera {im.camera_id}, which is not in {os.path.join(sparse, 'cameras' + ext)}")
        if im.camera_id not in intr:
            intr[im.camera_id] = camera_intrinsics(cams[im.camera_id], os.path.join(sparse, "cameras" + ext))
        path = os.path.join(images_dir, im.name)
        if not os.path.isfile(path):
            raise DatasetError(f"missing image {path} (listed in {images_path})")
        if not (np.all(np.isfinite(im.qvec)) and np.all(np.isfinite(im.tvec))) or np.linalg.norm(im.qvec) < 1e-12:
            raise DatasetError(f"{images_path}: non-finite pose for image {im.name}")
        frames.append(Frame(im.name, path, image_c2w(im), intr[im.camera_id]))
    points = np.stack([p.xyz for p in pts.values()]) if pts else None
    if points is not None:
        points = points[np.all(np.isfinite(points), axis=1)]
    return build_scene(frames, points, root, "colmap", images_path, name=name, split_lists=read_split_lists(root),
                       holdout=holdout, downscale=downscale, white_background=white_background, normalize=normalize,
                       unbounded=unbounded, ndc=ndc, pixels=pixels)
