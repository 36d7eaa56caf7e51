"""Scene names -> scenes: a dataset on disk wins over a built-in scene of the same name.

Resolution order for ``load_scene(name)`` with a data root (argument, else ``$WARPNERF_DATA``):

1. ``<root>/nerf_synthetic/<name>``, 2. ``<root>/nerf_llff_data/<name>``, 3. ``<root>/<name>``
   -- the first folder holding ``transforms_train.json`` (Blender), ``poses_bounds.npy`` (LLFF),
   ``transforms.json`` (nerfstudio / instant-ngp) or a COLMAP model in ``sparse/0`` (COLMAP);
4. the built-in scene ``<name>`` (generated and cached on first use);
5. otherwise a DatasetError listing the built-in and dataset scenes available.
"""

from __future__ import annotations

import os

from warpnerf.data.background import BACKGROUNDS, FIXED, SettledBackground, settle_background
from warpnerf.data.blender import load_blender
from warpnerf.data.builtin import FORWARD_FACING, GENERATOR_VERSION, builtin_scenes, cache_root, load_builtin
from warpnerf.data.errors import DatasetError
from warpnerf.data.llff import load_llff
from warpnerf.data.normalize import choose_ray_space
from warpnerf.data.scene import Scene
from warpnerf.geometry.rig import Rig, classify_rig

DATA_ENV = "WARPNERF_DATA"
_SUBDIRS = ("nerf_synthetic", "nerf_llff_data", "")


def data_root_from(data_root: str | None = None) -> str | None:
    """The data root in use: ``data_root``, else ``$WARPNERF_DATA``, else None.

    Raises DatasetError when the chosen root is not a folder (a typo should not silently fall
    back to a built-in scene).
    """
    if data_root:
        where = "--data-root"
    else:
        data_root, where = os.environ.get(DATA_ENV) or None, f"${DATA_ENV}"
    if data_root is None:
        return None
    data_root = os.path.abspath(os.path.expanduser(data_root))
    if not os.path.isdir(data_root):
        raise DatasetError(f"data root {data_root} (from {where}) is not a folder")
    return data_root


def scene_layout(folder: str) -> str | None:
    """"blender", "llff", "transforms", "colmap" or None, from the files in ``folder``."""
    if os.path.isfile(os.path.join(folder, "transforms_train.json")):
        return "blender"
    if os.path.isfile(os.path.join(folder, "poses_bounds.npy")):
        return "llff"
    if os.path.isfile(os.path.join(folder, "transforms.json")):
        return "transforms"
    from warpnerf.data.colmap import find_sparse  # lazy: the COLMAP reader stays out of --help

    if find_sparse(folder):
        return "colmap"
    return None


def find_dataset(name: str, data_root: str | None) -> tuple[str, str] | None:
    """(folder, layout) of dataset scene ``name`` under ``data_root``, or None."""
    if not data_root:
        return None
    for sub in _SUBDIRS:
        folder = os.path.join(data_root, sub, name)
        layout = scene_layout(folder)
        if layout:
            return folder, layout
    return None


def dataset_scenes(data_root: str | None) -> dict[str, tuple[str, str]]:
    """Name -> (folder, layout) of every dataset scene under ``data_root`` (first match wins)."""
    found: dict[str, tuple[str, str]] = {}
    if not data_root:
        return found
    for sub in _SUBDIRS:
        parent = os.path.join(data_root, sub)
        try:
            entries = sorted(os.listdir(parent))
        except OSError:
            continue
        for entry in entries:
            folder = os.path.join(parent, entry)
            layout = scene_layout(folder) if os.path.isdir(folder) else None
            if layout and entry not in found:
                found[entry] = (folder, layout)
    return found


def capture_rig(folder: str, layout: str) -> Rig:
    """The :class:`~warpnerf.geometry.rig.Rig` of the capture (layout "colmap" or "transforms") in ``folder``,
    from its pose file alone (no image is read). DatasetError when the poses cannot be read."""
    if layout == "colmap":
        from warpnerf.data.colmap import read_colmap_poses  # lazy: the COLMAP reader stays out of --help

        return classify_rig(read_colmap_poses(folder))
    from warpnerf.data.transforms_json import read_transforms_poses  # lazy: stays out of --help (it brings the COLMAP reader)

    return classify_rig(read_transforms_poses(folder))


def is_forward_facing(name: str, data_root: str | None = None, ndc: bool | None = None,
                      unbounded: bool | None = None) -> bool:
    """Whether scene ``name`` resolves (as :func:`load_scene` would) to a forward-facing scene, one
    trained in LLFF's NDC ray space: a dataset scene in the LLFF layout, a built-in forward-facing one,
    or a COLMAP / transforms.json capture whose rig is forward-facing (:func:`capture_rig`), or any
    capture with ``ndc`` True, unless ``ndc`` is False or ``unbounded`` True
    (:func:`~warpnerf.data.normalize.choose_ray_space`). Reads the capture's pose file, no image; an
    unusable data root or pose file counts as none (loading reports it)."""
    try:
        root = data_root_from(data_root)
    except DatasetError:
        root = None
    hit = find_dataset(name, root)
    if not hit:
        return name in FORWARD_FACING
    folder, layout = hit
    if layout in ("colmap", "transforms"):
        try:
            return choose_ray_space(capture_rig(folder, layout).kind, unbounded, ndc)[0] == "ndc"
        except (DatasetError, ValueError):  # a bad file, or --ndc with --unbounded: loading says so
            return False
    return layout == "llff"


def list_scenes(data_root: str | None = None) -> tuple[list[str], list[str]]:
    """(built-in scene names, dataset scene names under the data root)."""
    return list(builtin_scenes()), sorted(dataset_scenes(data_root_from(data_root)))


def load_scene(
    name: str,
    data_root: str | None = None,
    downscale: int = 1,
    splits: tuple[str, ...] = ("train", "val", "test"),
    white_background: bool = True,
    builtin_resolution: int | None = None,
    cache_dir: str | None = None,
    llff_factor: int = 8,
    llff_holdout: int = 8,
    llff_test: str = "every8",
    progress: bool = True,
    allow_rgb: bool = False,
    unbounded: bool | None = None,
    ndc: bool | None = None,
    background: str | None = None,
    pixels: bool = True,
    settled: SettledBackground | None = None,
) -> Scene:
    """Load scene ``name`` from the data root if it is there, else the built-in scene of that name.

    Args:
        name: scene name, e.g. "lego", "fern" or "chair".
        data_root: folder to search (default ``$WARPNERF_DATA``); see the module docstring.
        downscale: integer image downscale (all layouts).
        splits, white_background: Blender layouts (datasets and built-ins).
        builtin_resolution, cache_dir, progress: built-in scenes only (image side in pixels,
            default warpnerf.data.builtin.DEFAULT_RESOLUTION; cache folder; tqdm bar).
        llff_factor: LLFF only (``images_<factor>``).
        llff_test: LLFF only: "every8" (every ``llff_holdout``-th view) or "last10" (BARF's split;
            :func:`~warpnerf.data.llff.load_llff`'s ``test``).
        llff_holdout: LLFF, COLMAP and transforms.json: every n-th view is a test view (unless
            the files name a split).
        unbounded: COLMAP and transforms.json: a 360° capture with a distant background, trained
            in a contracted ray space (the built-in unbounded scenes always are); None: 360° rigs are
            (:func:`~warpnerf.data.normalize.choose_ray_space`).
        ndc: COLMAP and transforms.json: train in LLFF's NDC; None: forward-facing rigs do (LLFF
            scenes always do: False is refused for them, as True is for Blender-layout scenes).
        background: every layout: :data:`~warpnerf.data.background.BACKGROUNDS` (None: "auto"), applied by
            :func:`~warpnerf.data.background.settle_background`; "white" / "black" also choose what images
            with alpha are composited on (over ``white_background``).

        pixels: False: a cameras-only load (:mod:`warpnerf.data.scene`; for a viewer, which never trains):
            sizes from the image headers, no pixel decoded or resampled, stand-ins for the images, alpha and
            depth. Everything else (cameras, intrinsics, normalisation, bounds, ray space, splits, ids, checks)
            is the full load's. The background cannot be detected without pixels: ``settled`` is applied instead.
        settled: with ``pixels`` False (and only then), the :class:`~warpnerf.data.background.SettledBackground`
            the full load settled (a run folder's record); its mode must be ``background``'s.

    The scene's ``background_note`` says what was chosen (empty for images with alpha and "auto").

    Raises:
        DatasetError: unknown name (the message lists what exists) or any loader error.
    """
    if background is not None and background not in BACKGROUNDS:
        raise DatasetError(f"unknown background '{background}': expected one of {', '.join(BACKGROUNDS)}")
    if pixels == (settled is not None):
        raise ValueError("a cameras-only load (pixels=False) takes the settled background (settled=...), "
                         "a full load settles it from the pixels")
    if settled is not None and settled.mode != (background or "auto"):
        raise ValueError(f"the settled background was chosen by --background {settled.mode}, not {background or 'auto'}")
    if background in FIXED:
        white_background = background == "white"
    scene = _load(name, data_root, downscale, splits, white_background, builtin_resolution, cache_dir, llff_factor,
                  llff_holdout, llff_test, progress, allow_rgb, unbounded, ndc, pixels)
    return settle_background(scene, background) if pixels else settled.apply(scene)


def _load(name, data_root, downscale, splits, white_background, builtin_resolution, cache_dir, llff_factor,
          llff_holdout, llff_test, progress, allow_rgb, unbounded, ndc, pixels=True) -> Scene:
    """:func:`load_scene` before the background is settled."""
    root = data_root_from(data_root)
    hit = find_dataset(name, root)
    if hit:
        folder, layout = hit
        if ndc is not None and layout in ("blender", "llff") and ndc != (layout == "llff"):
            raise DatasetError(f"scene '{name}' is in the {'LLFF' if layout == 'llff' else 'Blender'} layout, which "
                               f"trains {'in NDC only' if layout == 'llff' else 'in a box only'}; "
                               f"--ndc / --no-ndc choose for COLMAP and transforms.json captures")
        if layout == "blender":
            return load_blender(folder, downscale=downscale, splits=splits, white_background=white_background, name=name,
                                allow_rgb=allow_rgb, pixels=pixels)
        if layout == "transforms":
            from warpnerf.data.transforms_json import load_transforms_json  # lazy: stays out of --help (it brings the COLMAP reader)

            return load_transforms_json(folder, downscale=downscale, holdout=llff_holdout,
                                        white_background=white_background, name=name, unbounded=unbounded, ndc=ndc,
                                        pixels=pixels)
        if layout == "colmap":
            from warpnerf.data.colmap import load_colmap  # lazy: the COLMAP reader stays out of --help

            return load_colmap(folder, downscale=downscale, holdout=llff_holdout, white_background=white_background,
                               name=name, unbounded=unbounded, ndc=ndc, pixels=pixels)
        return load_llff(folder, factor=llff_factor, holdout=llff_holdout, downscale=downscale, name=name,
                         test=llff_test, pixels=pixels)
    if name in builtin_scenes():
        if ndc is not None and ndc != (name in FORWARD_FACING):
            raise DatasetError(f"the built-in scene '{name}' trains {'in NDC' if name in FORWARD_FACING else 'without NDC'} "
                               f"only; --ndc / --no-ndc choose for COLMAP and transforms.json captures")
        return load_builtin(
            name,
            resolution=builtin_resolution,
            cache_dir=cache_dir,
            downscale=downscale,
            splits=splits,
            white_background=white_background,
            progress=progress,
            pixels=pixels,
        )
    datasets = sorted(dataset_scenes(root))
    where = (
        f"dataset scenes under {root}: {', '.join(datasets) if datasets else 'none'}"
        if root
        else f"no data root (pass --data-root or set {DATA_ENV} for NeRF-synthetic/LLFF scenes)"
    )
    raise DatasetError(f"unknown scene '{name}'; built-in scenes: {', '.join(builtin_scenes())}; {where}")


def describe_scenes(data_root: str | None = None, cache_dir: str | None = None) -> str:
    """Text for ``warpnerf scenes``: built-in scenes (with cached resolutions) and dataset scenes."""
    cache = cache_root(cache_dir)
    try:
        cached_entries = os.listdir(cache)
    except OSError:
        cached_entries = []
    lines = [f"Built-in scenes (rendered on first use, cached in {cache}):"]
    builtins = builtin_scenes()
    width = max(len(n) for n in builtins)
    for name, desc in builtins.items():
        # Folder names: <name>_<res>px_g<version>[_n...]; only finished, current-version ones count.
        suffix = f"px_g{GENERATOR_VERSION}"
        res = sorted(
            {
                e[len(name) + 1 :].split(suffix)[0]
                for e in cached_entries
                if e.startswith(name + "_") and suffix in e and os.path.isfile(os.path.join(cache, e, ".complete"))
            },
            key=lambda r: int(r) if r.isdigit() else 0,
        )
        cached = f"  [cached: {', '.join(r + 'px' for r in res)}]" if res else ""
        lines.append(f"  {name:<{width}}  {desc}{cached}")
    try:
        root = data_root_from(data_root)
    except DatasetError as exc:
        lines.append(f"Dataset scenes: {exc}")
        return "\n".join(lines)
    if root is None:
        lines.append(f"Dataset scenes: no data root (pass --data-root or set {DATA_ENV}).")
        return "\n".join(lines)
    found = dataset_scenes(root)
    lines.append(f"Dataset scenes under {root}:" if found else f"Dataset scenes under {root}: none found")
    width = max((len(n) for n in found), default=0)
    for name, (folder, layout) in sorted(found.items()):
        shadow = "  (overrides the built-in scene)" if name in builtins else ""
        lines.append(f"  {name:<{width}}  {layout:<10}  {folder}{shadow}")
    return "\n".join(lines)
