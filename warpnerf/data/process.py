"""``warpnerf process --images DIR | --video FILE --out DATASET``: photos -> COLMAP poses -> a scene folder.

``--video FILE`` first extracts about ``--num-frames`` frames (imageio-ffmpeg, ``pip install
'warpnerf[video]'``): the video's frames are split into that many equal windows of consecutive frames
and the sharpest frame of each (largest variance of the Laplacian of its grey image) is kept, so
motion-blurred frames are left out. They become ``DATASET/images/frame_00001.png, ...`` and the
photo pipeline below runs on them (sequential matching by default).

Runs COLMAP's structure from motion (SIFT feature extraction, exhaustive or sequential matching,
incremental mapping) through pycolmap (``pip install 'warpnerf[colmap]'``), else through the
``colmap`` program when it is on the PATH, and writes what :func:`warpnerf.data.colmap.load_colmap`
reads::

    DATASET/images/...           # copies of the photos
    DATASET/images_2/, images_4/ # the photos downscaled 2x, 4x (as nerfstudio writes them; --num-downscales)
    DATASET/sparse/0/*.bin       # the largest reconstruction
    DATASET/colmap/database.db   # features and matches (kept for re-runs / inspection)
    DATASET/.warpnerf-process    # marker: made by warpnerf process (``--overwrite`` re-makes only such folders)

``DATASET`` must be new or empty (the photos' own folder ``DATASET/images`` aside, when processed in
place); a previous output of ``warpnerf process`` is re-made only with ``overwrite``, and anything else
is refused before a file is written.

Mapping that registers fewer than ``min_registered`` images is an error saying how many
registered; a partial registration is reported on stderr and the dataset is still written
(unregistered photos are left out of the model, so the loader skips them). When sequential matching
registers under :data:`REGISTERED_WARN` of the photos, matching is re-run exhaustively once on the same
features (said in one line) and the reconstruction that registers more images is kept; under that
fraction in the end, a one-line warning names what to try.

The result also gives the model's mean reprojection error (pixels) and the rig the registered cameras
form (:func:`warpnerf.geometry.rig.classify_rig`: object, forward-facing or 360, with its reason), read
back from the written model as the COLMAP loader reads it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time

import numpy as np
from tqdm.auto import tqdm

from warpnerf.data.errors import DatasetError
from warpnerf.data.images import IMAGE_SUFFIXES

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MARKER = ".warpnerf-process"  # in DATASET: warpnerf process wrote this folder
MAX_DOWNSCALES = 3  # images_2, images_4, images_8
# what process writes in DATASET (besides the marker)
OUTPUTS = ("images", "sparse", "colmap") + tuple(f"images_{2 ** k}" for k in range(1, MAX_DOWNSCALES + 1))
DEFAULT_NUM_FRAMES = 100  # --video: frames kept (one per window of consecutive frames)
MATCHERS = ("exhaustive", "sequential")
# under this fraction of the photos registered: sequential matching falls back to exhaustive, then a warning
# (nerfstudio warns likewise when few images register)
REGISTERED_WARN = 0.8


def list_images(folder: str) -> list[str]:
    if not os.path.isdir(folder):
        raise DatasetError(f"image folder not found: {folder}")
    names = sorted(f for f in os.listdir(folder) if os.path.splitext(f)[1].lower() in IMAGE_SUFFIXES)
    if not names:
        raise DatasetError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    return names


def check_out(out: str, images: str, overwrite: bool = False) -> list[str]:
    """Refuse (DatasetError, one line) an ``out`` that exists and is not a folder, or that holds anything
    but the input photos themselves (``out/images`` processed in place), unless it is an earlier output
    of ``warpnerf process`` (its marker) and ``overwrite`` is given. Returns the entries to remove first."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise DatasetError(f"--out {out} exists and is not a folder")
    if not os.path.isdir(out):
        return []
    in_place = os.path.abspath(images) == os.path.abspath(os.path.join(out, "images"))
    entries = sorted(n for n in os.listdir(out) if not (in_place and n == "images"))
    if not entries:
        return []
    if not os.path.isfile(os.path.join(out, MARKER)):
        raise DatasetError(f"--out {out} is not empty ({', '.join(entries[:3])}{', ...' if len(entries) > 3 else ''}) "
                           f"and was not written by warpnerf process (no {MARKER}); choose a new or empty folder")
    if not overwrite:
        raise DatasetError(f"--out {out} holds an earlier warpnerf process output; pass --overwrite to re-make it "
                           "or choose another folder")
    return [n for n in entries if n in OUTPUTS]


def backend() -> str:
    """"pycolmap", "colmap" (the program) or raise DatasetError saying how to get one."""
    try:
        import pycolmap  # noqa: F401  # optional extra: warpnerf[colmap]

        return "pycolmap"
    except ImportError:
        pass
    if shutil.which("colmap"):
        return "colmap"
    raise DatasetError("warpnerf process needs COLMAP: pip install 'warpnerf[colmap]' (pycolmap), or put the colmap program on the PATH")


def _start_out(out: str, stale: list[str]) -> None:
    """Remove an earlier output's entries ``stale`` and (re)write the marker."""
    for name in stale:  # an earlier output being re-made: its images, model and database go
        path = os.path.join(out, name)
        if os.path.isdir(path):
            shutil.rmtree(path)
        else:
            os.unlink(path)
    try:
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, MARKER), "w") as fh:
            fh.write("written by warpnerf process; --overwrite may re-make this folder\n")
    except OSError as e:
        raise DatasetError(f"--out {out} cannot be written: {e.strerror or e}; choose another folder") from None


def write_downscaled(out: str, num_downscales: int) -> None:
    """``out/images_2``, ``images_4``, ... (``num_downscales`` of them): each photo of ``out/images``
    shrunk by 2, 4, ... (box filter, sizes rounded down, at least 1 pixel), same file names."""
    from PIL import Image  # lazy: only when downscaled copies are written

    src = os.path.join(out, "images")
    for k in range(1, num_downscales + 1):
        f = 2 ** k
        dst = os.path.join(out, f"images_{f}")
        os.makedirs(dst, exist_ok=True)
        for name in list_images(src):
            with Image.open(os.path.join(src, name)) as im:
                size = (max(im.width // f, 1), max(im.height // f, 1))
                im.resize(size, Image.BOX).save(os.path.join(dst, name))


def sharpness(frame: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the frame's grey image: larger is sharper."""
    g = np.asarray(frame, np.float32)
    if g.ndim == 3:
        g = g[..., :3].mean(-1)
    lap = 4 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]
    return float(lap.var()) if lap.size else 0.0


def _video_reader(video: str):
    if not os.path.isfile(video):
        raise DatasetError(f"video not found: {video}")
    try:
        import imageio_ffmpeg  # noqa: F401  # optional extra: warpnerf[video]
    except ImportError:
        raise DatasetError("warpnerf process --video needs imageio-ffmpeg: pip install 'warpnerf[video]'") from None
    import imageio.v2 as iio  # lazy: only --video reads videos

    try:
        return iio.get_reader(video, format="FFMPEG")
    except Exception as e:  # noqa: BLE001  (imageio/ffmpeg raise many kinds for a file that is not a video)
        raise DatasetError(f"cannot read video {video}: {str(e).strip().splitlines()[0] if str(e).strip() else e}") from None


def extract_frames(video: str, folder: str, num_frames: int = DEFAULT_NUM_FRAMES, progress: bool = True) -> dict:
    """Write about ``num_frames`` frames of ``video`` to ``folder`` as frame_00001.png, ...: the video's
    frames split into ``num_frames`` equal windows of consecutive frames (every frame when it has fewer),
    the sharpest (:func:`sharpness`) of each. One window's best frame is held in memory at a time.

    Returns {"frames": written, "video_frames": frames read, "picked": [index of each written frame]}."""
    if num_frames < 1:
        raise DatasetError(f"--num-frames must be >= 1, got {num_frames}")
    from imageio.v2 import imwrite  # lazy: only --video reads videos

    reader = _video_reader(video)
    with reader:
        try:
            n = int(reader.count_frames())
        except Exception:  # noqa: BLE001  (a stream ffmpeg cannot count: one window per frame)
            n = 0
        windows = min(num_frames, n) if n > 0 else num_frames
        os.makedirs(folder, exist_ok=True)
        picked: list[int] = []
        best = None  # (score, frame index, frame) of the current window
        window = -1

        def flush():
            if best is not None:
                picked.append(best[1])
                imwrite(os.path.join(folder, f"frame_{len(picked):05d}.png"), best[2])

        read = 0
        for i, frame in enumerate(tqdm(reader, total=n or None, desc="video: frames", unit="frame",
                                       disable=not progress, dynamic_ncols=True)):
            read = i + 1
            w = min(i * windows // n, windows - 1) if n > 0 else i
            if w != window:
                flush()
                best, window = None, w
            score = sharpness(frame)
            if best is None or score > best[0]:
                best = (score, i, np.asarray(frame))
        flush()
    if not picked:
        raise DatasetError(f"no frame could be read from {video}")
    return {"frames": len(picked), "video_frames": read, "picked": picked}


def process_video(video: str, out: str, num_frames: int = DEFAULT_NUM_FRAMES, overwrite: bool = False,
                  progress: bool = True, use: str | None = None, num_downscales: int = 2, **kwargs) -> dict:
    """Extract the sharpest ~``num_frames`` frames of ``video`` into ``out/images``
    (:func:`extract_frames`), then :func:`process_images` on them (``kwargs``: its options).

    Returns process_images' dict plus "video_frames" (frames the video has)."""
    if num_frames < 3:
        raise DatasetError(f"--num-frames must be >= 3 (COLMAP needs several views), got {num_frames}")
    if not 0 <= num_downscales <= MAX_DOWNSCALES:
        raise DatasetError(f"--num-downscales must be 0..{MAX_DOWNSCALES}, got {num_downscales}")
    _video_reader(video).close()  # a missing file or extra fails before --out is touched
    stale = check_out(out, video, overwrite)
    which = use or backend()
    _start_out(out, stale)
    frames = extract_frames(video, os.path.join(out, "images"), num_frames, progress)
    # out now holds only the marker and the frames: process them in place
    res = process_images(os.path.join(out, "images"), out, use=which, progress=progress, overwrite=True,
                         num_downscales=num_downscales, **kwargs)
    res["video_frames"] = frames["video_frames"]
    return res


def process_images(
    images: str,
    out: str,
    camera_model: str = "SIMPLE_RADIAL",
    camera_params: str | None = None,
    single_camera: bool = True,
    matcher: str = "exhaustive",
    max_image_size: int = 1600,
    min_registered: int = 3,
    threads: int = -1,
    seed: int = 0,
    use: str | None = None,
    progress: bool = True,
    overwrite: bool = False,
    num_downscales: int = 2,
) -> dict:
    """Run structure from motion on the photos in ``images`` and write the dataset ``out``.

    Args:
        camera_model: COLMAP model to estimate (one the loaders support).
        camera_params: known intrinsics as COLMAP's comma-separated parameter list (then kept fixed).
        single_camera: one shared camera for all photos (one device, fixed zoom).
        matcher: "exhaustive" (up to a few hundred photos) or "sequential" (video frames).
        max_image_size: longest side SIFT sees, pixels.
        min_registered: fewer registered images is an error.
        use: force "pycolmap" or "colmap" (default: what is installed).
        overwrite: re-make ``out`` when it is an earlier output of this command (see :func:`check_out`).
        num_downscales: also write ``images_2``, ``images_4``, ... (that many; 0: none).

    Returns {"images": N, "registered": M, "points": P, "reprojection_error": mean px, "rig": kind,
    "rig_reason": one line, "matching": matcher of the kept model, "fallback": exhaustive re-run or not,
    "seconds": t, "backend": name}.
    """
    if camera_model not in CAMERA_MODELS:
        raise DatasetError(f"--camera-model {camera_model} is not one warpnerf loads ({', '.join(CAMERA_MODELS)})")
    if matcher not in MATCHERS:
        raise DatasetError(f"--matching must be exhaustive or sequential, got {matcher}")
    if not 0 <= num_downscales <= MAX_DOWNSCALES:
        raise DatasetError(f"--num-downscales must be 0..{MAX_DOWNSCALES}, got {num_downscales}")
    names = list_images(images)
    stale = check_out(out, images, overwrite)
    which = use or backend()
    t0 = time.time()
    _start_out(out, stale)
    work = os.path.join(out, "colmap")
    img_out = os.path.join(out, "images")
    if os.path.abspath(images) != os.path.abspath(img_out):
        os.makedirs(img_out, exist_ok=True)
        for n in names:
            shutil.copy2(os.path.join(images, n), os.path.join(img_out, n))
    os.makedirs(work, exist_ok=True)
    db = os.path.join(work, "database.db")
    if os.path.exists(db):
        os.remove(db)  # stale features of another image set would be matched too
    models = os.path.join(work, "sparse")
    shutil.rmtree(models, ignore_errors=True)
    os.makedirs(models)

    def reconstruct(how: str, extract: bool, sub: str) -> dict:
        """One pass of matching (``how``) and mapping into ``models/sub``; features extracted first if ``extract``."""
        folder = os.path.join(models, sub)
        os.makedirs(folder)
        bar = tqdm(total=3 + len(names), desc="colmap: features" if extract else "colmap: matching", unit="step",
                   disable=not progress, dynamic_ncols=True)
        with bar:
            if which == "pycolmap":
                rec = _run_pycolmap(img_out, db, folder, names, camera_model, camera_params, single_camera, how,
                                    max_image_size, threads, seed, bar, extract=extract)
                if rec is None:
                    return {"registered": 0, "points": 0, "error": float("nan"), "write": None, "matching": how}
                return {"registered": int(rec.num_reg_images()), "points": int(rec.num_points3D()),
                        "error": float(rec.compute_mean_reprojection_error()), "write": rec.write, "matching": how}
            return _run_colmap_program(img_out, db, folder, camera_model, camera_params, single_camera, how,
                                       max_image_size, bar, extract=extract) | {"matching": how}

    best = reconstruct(matcher, True, "0")
    fallback = matcher == "sequential" and best["registered"] < REGISTERED_WARN * len(names)
    if fallback:
        print(f"warpnerf process: sequential matching registered {best['registered']} of {len(names)} images "
              f"(under {100 * REGISTERED_WARN:.0f} %): matching exhaustively once and keeping the better model", file=sys.stderr)
        again = reconstruct("exhaustive", False, "1")
        if again["registered"] > best["registered"]:
            best = again
    registered = best["registered"]
    if registered < min_registered:
        raise DatasetError(
            f"COLMAP mapping failed: {registered} of {len(names)} images in {images} registered (need {min_registered}); "
            "photos need overlap (each point seen from several views) and texture"
        )
    sparse = os.path.join(out, "sparse", "0")
    shutil.rmtree(sparse, ignore_errors=True)
    os.makedirs(sparse)
    best["write"](sparse)
    if registered < REGISTERED_WARN * len(names):
        # sequential matching has fallen back to exhaustive by now: what is left to try is the photos
        print(f"warpnerf process: warning: only {registered} of {len(names)} images registered "
              f"({100 * registered / len(names):.0f} %, under {100 * REGISTERED_WARN:.0f} %) with --matching exhaustive"
              f"{' (tried after sequential)' if fallback else ''}; the others are left out: retake with more overlap "
              "between neighbouring photos (each part of the scene in 3+ views) and more texture", file=sys.stderr)
    elif registered < len(names):
        print(f"warpnerf process: {registered} of {len(names)} images registered; the others are left out", file=sys.stderr)
    from warpnerf.data.colmap import read_colmap_poses  # lazy: the COLMAP reader stays out of --help
    from warpnerf.geometry.rig import classify_rig  # lazy: only a finished reconstruction is classified

    rig = classify_rig(read_colmap_poses(out))  # the registered cameras, converted as the loader converts them
    write_downscaled(out, num_downscales)
    return {"images": len(names), "registered": int(registered), "points": int(best["points"]),
            "reprojection_error": float(best["error"]), "rig": rig.kind, "rig_reason": rig.reason,
            "matching": best["matching"], "fallback": fallback,
            "seconds": round(time.time() - t0, 1), "backend": which}


def _run_pycolmap(img_dir, db, models, names, camera_model, camera_params, single_camera, matcher, max_image_size,
                  threads, seed, bar, extract=True):
    """Features (when ``extract``; else those in ``db``), ``matcher`` matching and mapping into ``models``:
    the reconstruction that registers most images, or None."""
    import pycolmap  # optional extra: warpnerf[colmap]

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_params:
        reader.camera_params = camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.num_threads = threads
    extraction.use_gpu = False
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
    if extract:
        pycolmap.extract_features(db, img_dir, image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
    bar.update(1)
    bar.set_description("colmap: matching")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = False
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_sequential(db, matching_options=matching, device=pycolmap.Device.cpu)
    bar.update(1)
    bar.set_description("colmap: mapping")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = threads
    opts.random_seed = seed
    if camera_params:  # known intrinsics stay fixed
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
    recs = pycolmap.incremental_mapping(db, img_dir, models, options=opts,
                                        initial_image_pair_callback=lambda: bar.update(2),
                                        next_image_callback=lambda: bar.update(1))
    bar.set_description("colmap: done")
    bar.update(bar.total - bar.n)
    if not recs:
        return None
    return max(recs.values(), key=lambda r: r.num_reg_images())


def _run_colmap_program(img_dir, db, models, camera_model, camera_params, single_camera, matcher, max_image_size, bar,
                        extract=True):
    """As :func:`_run_pycolmap` through the ``colmap`` program: {"registered", "points", "error" (mean
    reprojection error, px), "write" (copies the largest model into a folder, None without one)}."""
    def run(*args):
        proc = subprocess.run(["colmap", *args], capture_output=True, text=True)
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            raise DatasetError(f"colmap {args[0]} failed (exit {proc.returncode}): {tail[0]}")

    extra = ["--ImageReader.camera_params", camera_params] if camera_params else []
    if extract:
        run("feature_extractor", "--database_path", db, "--image_path", img_dir, "--ImageReader.camera_model", camera_model,
            "--ImageReader.single_camera", str(int(single_camera)), "--SiftExtraction.use_gpu", "0",
            "--SiftExtraction.max_image_size", str(max_image_size), *extra)
    bar.update(1)
    run(f"{matcher}_matcher", "--database_path", db, "--SiftMatching.use_gpu", "0")
    bar.update(1)
    run("mapper", "--database_path", db, "--image_path", img_dir, "--output_path", models)
    bar.update(bar.total - bar.n)
    from warpnerf.data.colmap import read_model  # lazy: the COLMAP reader stays out of --help

    best = {"registered": 0, "points": 0, "error": float("nan"), "write": None}
    for sub in sorted(os.listdir(models)):
        folder = os.path.join(models, sub)
        try:
            _, imgs, pts = read_model(folder)
        except DatasetError:
            continue
        if len(imgs) > best["registered"]:
            obs = sum(len(p.image_ids) for p in pts.values())  # COLMAP's mean: over observations
            err = sum(p.error * len(p.image_ids) for p in pts.values()) / obs if obs else float("nan")
            best = {"registered": len(imgs), "points": len(pts), "error": err,
                    "write": lambda dst, src=folder: shutil.copytree(src, dst, dirs_exist_ok=True)}
    return best


# ---- CLI ----------------------------------------------------------------------------------------


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("process", help="photos or a video -> COLMAP camera poses -> a dataset folder warpnerf trains on")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", help="folder of photos")
    src.add_argument("--video", help="video file: its sharpest frame of each of --num-frames windows becomes a photo "
                                     "(needs pip install 'warpnerf[video]')")
    p.add_argument("--num-frames", type=int, default=DEFAULT_NUM_FRAMES, help="--video: frames to extract")
    p.add_argument("--out", required=True, help="dataset folder to write (images/, images_2/, images_4/, sparse/0/, colmap/)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=CAMERA_MODELS)
    p.add_argument("--camera-params", default=None, help="known intrinsics, COLMAP order, comma-separated (kept fixed)")
    p.add_argument("--per-image-camera", action="store_true", help="estimate a camera per photo (mixed devices/zoom)")
    p.add_argument("--matching", "--matcher", dest="matcher", default=None, choices=MATCHERS,
                   help="feature matching (--matcher is the same flag); default: sequential for --video, exhaustive "
                        f"for --images; sequential registering under {100 * REGISTERED_WARN:.0f} %% of the images is re-run "
                        "exhaustively once")
    p.add_argument("--max-image-size", type=int, default=1600)
    p.add_argument("--num-downscales", type=int, default=2,
                   help=f"also write images_2, images_4, ... (that many, 0..{MAX_DOWNSCALES}; 0: none)")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--overwrite", action="store_true",
                   help="re-make --out when it holds an earlier 'warpnerf process' output (other folders: never)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    opts = dict(camera_model=args.camera_model, camera_params=args.camera_params,
                single_camera=not args.per_image_camera, max_image_size=args.max_image_size, progress=not args.quiet,
                overwrite=args.overwrite, num_downscales=args.num_downscales)
    if args.video:
        res = process_video(args.video, args.out, args.num_frames, matcher=args.matcher or "sequential", **opts)
        print(f"video: {res['images']} frames kept of {res['video_frames']} (the sharpest of each window)")
    else:
        res = process_images(args.images, args.out, matcher=args.matcher or "exhaustive", **opts)
    print(f"registered {res['registered']} of {res['images']} images, {res['points']} points, "
          f"mean reprojection error {res['reprojection_error']:.2f} px, rig {res['rig']}, "
          f"{res['seconds']} s ({res['backend']}, {res['matching']} matching)")
    print(f"rig: {res['rig_reason']}")
    print(f"dataset: {os.path.abspath(args.out)}  (train with: warpnerf train --scene {os.path.basename(os.path.normpath(args.out))} "
          f"--data-root {os.path.dirname(os.path.abspath(args.out))})")
    return 0
