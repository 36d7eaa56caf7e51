"""Command-line parsers of the commands that work on a finished run: ``render``, ``export``, ``view``.

Kept apart from the modules that do the work so ``warpnerf --help`` does not import torch;
each command imports its module when it runs. Errors the user can fix raise ``UserError``
(one line, exit code 2).
"""

from __future__ import annotations

import argparse
import json
import os
import time

from warpnerf.cli.errors import UserError
from warpnerf.cli.recording import Recorder, add_record_flags
from warpnerf.runs import record


def _run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", required=True, help="run folder written by 'warpnerf train'")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def add_output_commands(sub) -> None:
    """Register ``render``, ``export`` and ``view`` on the ``warpnerf`` sub-parser set ``sub``."""
    p = sub.add_parser("render", help="render a camera path of a trained run to MP4 (GIF without ffmpeg)")
    _run_args(p)
    p.add_argument("--path", default="orbit", help="orbit, spiral, test, or a nerfstudio camera_path.json")
    p.add_argument("--frames", type=int, default=60, help="frames (orbit/spiral; test: at most the test views)")
    p.add_argument("--out", default=None, help="video file (default RUN/render_<path>.mp4)")
    p.add_argument("--fps", type=float, default=24.0)
    p.add_argument("--scale", type=float, default=1.0, help="resolution relative to the training views")
    p.add_argument("--depth", action="store_true", help="depth map beside the RGB")
    p.add_argument("--save-path", default=None, help="also write the cameras as a nerfstudio camera_path.json")
    p.set_defaults(func=cmd_render)

    e = sub.add_parser("export", help="export a trained run's geometry: marching-cubes mesh or point cloud (PLY)")
    _run_args(e)
    e.add_argument("--what", default="mesh", choices=["mesh", "points"])
    e.add_argument("--out", default=None, help="PLY file (default RUN/<what>.ply)")
    e.add_argument("--resolution", type=int, default=256, help="mesh: density samples per axis of the scene box")
    e.add_argument("--threshold", type=float, default=None,
                   help="mesh: iso-level, density per scene unit (default: warpnerf.outputs.export.DEFAULT_THRESHOLD)")
    e.add_argument("--min-component-faces", type=int, default=None, metavar="N",
                   help="mesh: drop connected pieces with fewer faces, floaters (default: "
                        "warpnerf.outputs.export.DEFAULT_MIN_COMPONENT_FACES, 100; the largest piece always stays)")
    e.add_argument("--keep-floaters", action="store_true", help="mesh: keep every connected piece")
    e.add_argument("--scale", type=float, default=0.5, help="points: render resolution relative to the training views")
    e.add_argument("--min-opacity", type=float, default=0.95, help="points: keep pixels at least this opaque")
    e.add_argument("--max-points", type=int, default=1_000_000)
    e.add_argument("--max-views", type=int, default=0, help="points: render at most this many training views (0: all)")
    add_record_flags(e, "the export's counts, time and peak memory (<out>.export.json) and the run's metrics and "
                        "config")
    e.set_defaults(func=cmd_export)

    v = sub.add_parser("view", help="live viewer of a run in the browser (viser); follows a training run's checkpoints")
    _run_args(v)
    v.add_argument("--host", default="127.0.0.1", help="interface to serve on (0.0.0.0: reachable from other machines)")
    v.add_argument("--port", type=int, default=8080)
    v.add_argument("--preview-height", type=int, default=None,
                   help="full render height in pixels, once the view is still (the window's, if smaller; while "
                        "it moves: a quarter of it); the panel's max height starts here. Default: the window's "
                        "height on a GPU, 160 on a CPU")
    v.add_argument("--max-size", default="1920x1080",
                   help="WIDTHxHEIGHT no render exceeds, whatever canvas a browser reports (aspect kept)")
    v.add_argument("--max-pixels", type=int, default=1920 * 1080, help="pixel budget of one render")
    v.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="also accept browsers whose page comes from ORIGIN (e.g. http://myhost:9000; '*': any); "
                        "by default only the viewer's own page may connect")
    v.add_argument("--wait", type=float, default=0.0,
                   help="seconds to wait for checkpoint.pt of a training run that has not saved one yet")
    v.set_defaults(func=cmd_view)


def cmd_render(args) -> int:
    from warpnerf.runs.folder import load_run  # lazy: keeps --help fast (torch)
    from warpnerf.runs.video import (PathError, check_render_memory, make_path,  # lazy: keeps --help fast (torch)
                                     render_frames, write_camera_path_json, write_video)

    if args.fps <= 0 or args.scale <= 0:
        raise UserError("--fps and --scale must be > 0")
    if args.path.endswith(".json") and not os.path.isfile(args.path):
        raise UserError(f"camera path file not found: {args.path}")
    trainer = load_run(args.run, args.device, progress=not args.quiet)
    name = os.path.splitext(os.path.basename(args.path))[0]
    out = args.out or os.path.join(args.run, f"render_{name}.mp4")
    try:
        cams = make_path(trainer, args.path, args.frames, args.scale)
        check_render_memory(trainer, cams, args.depth)  # before a frame is rendered
    except PathError as e:
        raise UserError(str(e)) from e
    if args.save_path:
        write_camera_path_json(args.save_path, cams, args.fps)
    written = write_video(out, render_frames(trainer, cams, args.depth, not args.quiet), args.fps)
    print(f"{len(cams)} frames ({cams.width}x{cams.height}{' + depth' if args.depth else ''}) written to {written}")
    return 0


def cmd_export(args) -> int:
    from warpnerf.outputs.export import (DEFAULT_MIN_COMPONENT_FACES,  # lazy: keeps --help fast (torch)
                                         DEFAULT_THRESHOLD, ExportError, extract_mesh, extract_points, info_path,
                                         write_ply)
    from warpnerf.runs.folder import load_run  # lazy: keeps --help fast (torch)
    from warpnerf.train.checkpoint import atomic_write_text  # lazy: keeps --help fast (torch)
    from warpnerf.train.trainer import peak_rss_mb, start_memory_window  # lazy: keeps --help fast (torch)

    if args.resolution < 8 or args.scale <= 0 or args.max_points < 1:
        raise UserError("need --resolution >= 8, --scale > 0 and --max-points >= 1")
    if args.keep_floaters and args.min_component_faces is not None:
        raise UserError("--keep-floaters keeps every piece: leave out --min-component-faces")
    if args.min_component_faces is not None and args.min_component_faces < 1:
        raise UserError("need --min-component-faces >= 1 (--keep-floaters keeps every piece)")
    out = args.out or os.path.join(args.run, f"{args.what}.ply")
    recorder = Recorder(args, "export")  # a record that could not be written fails before any work (one line)
    trainer = load_run(args.run, args.device, progress=not args.quiet)
    info = {"what": args.what, "run": args.run, "out": out, "peak_rss_mb_load": round(peak_rss_mb(), 1)}
    start_memory_window()  # from here the peak is the export's (the loaded run stays resident)
    t0 = time.perf_counter()
    try:
        if args.what == "mesh":
            threshold = DEFAULT_THRESHOLD if args.threshold is None else args.threshold
            min_faces = (1 if args.keep_floaters else DEFAULT_MIN_COMPONENT_FACES if args.min_component_faces is None
                         else args.min_component_faces)
            mesh = extract_mesh(trainer, args.resolution, threshold, min_faces)
            write_ply(out, mesh.verts, mesh.colors, mesh.faces, mesh.normals)
            info.update(resolution=args.resolution, threshold=threshold, min_component_faces=min_faces, **mesh.counts)
            print(f"mesh: {mesh.summary}, iso-level {threshold}, written to {out}")
        else:
            points, colors = extract_points(trainer, args.scale, args.min_opacity, args.max_points,
                                            max_views=args.max_views)
            if len(points) == 0:
                raise ExportError(f"no pixel is more opaque than --min-opacity {args.min_opacity}")
            write_ply(out, points, colors)
            info.update(scale=args.scale, min_opacity=args.min_opacity, max_views=args.max_views, points=len(points))
            print(f"points: {len(points)} coloured points written to {out}")
    except ExportError as e:
        raise UserError(str(e)) from e
    info.update(export_seconds=round(time.perf_counter() - t0, 2), peak_rss_mb=round(peak_rss_mb(), 1))
    atomic_write_text(info_path(out), json.dumps(info, indent=1, sort_keys=True) + "\n")
    if recorder.path:  # the export's own record holds no run row: the run it read is its source
        recorder.write([], extra={"export": info, "source_run": record.read_run_files(args.run)})
    return 0


def cmd_view(args) -> int:
    try:
        import viser  # noqa: F401  # optional extra: warpnerf[viewer]
    except ImportError:
        raise UserError("warpnerf view needs viser: pip install 'warpnerf[viewer]'") from None
    from warpnerf.outputs.viewer import (RunViewer, parse_size, serve, view_url,  # lazy: keeps --help fast (torch)
                                         wait_for_checkpoint)

    try:
        max_size = parse_size(args.max_size)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.max_pixels < 256 or not (args.preview_height is None or 1 <= args.preview_height <= max_size[1]):
        raise UserError(f"need --max-pixels >= 256 and 1 <= --preview-height <= {max_size[1]} (--max-size height)")
    if not 0 <= args.port <= 65535:
        raise UserError(f"--port {args.port}: must be 0..65535")
    if args.wait > 0 and not wait_for_checkpoint(args.run, args.wait):
        raise UserError(f"no checkpoint.pt appeared in {args.run} within {args.wait:.0f} s")
    viewer = RunViewer(args.run, args.device, args.preview_height, max_size=max_size, max_pixels=args.max_pixels)

    def announce(port: int) -> None:  # the port viser bound: the next free one when --port is busy
        moved = f"; port {args.port} was busy" if args.port not in (0, port) else ""
        print(f"warpnerf view: {view_url(args.host, port)} (step {viewer.step}{moved}; Ctrl-C to stop)", flush=True)

    serve(viewer, args.host, args.port, allow_origins=args.allow_origin, announce=announce)
    return 0
