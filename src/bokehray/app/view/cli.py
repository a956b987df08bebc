"""The ``bokehray view`` subcommand (registered by :mod:`bokehray.app.cli`)."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys

from ...errors import InputError


def add_parser(sub) -> argparse.ArgumentParser:
    v = sub.add_parser(
        "view",
        help="interactive refocus page in the browser: click to focus, drag the aperture, export (docs/view.md)",
        description="Starts a local server (127.0.0.1, a free port unless --port) and prints its URL. The page "
        "starts from what `bokehray render` would do with the same inputs, shows a reduced-resolution preview after every "
        "change, then the sharp version at the size the screen shows, and "
        "exports what `bokehray render` writes, showing the command line that reproduces it. Needs the 'view' "
        "extra: pip install 'bokehray[view]'.",
    )
    v.add_argument("image", help="all-in-focus image: PNG/JPEG/TIFF (sRGB, 8/16-bit) or EXR/float TIFF (linear)")
    src = v.add_mutually_exclusive_group(required=True)
    src.add_argument("--disparity", help="disparity map in [0, 1], 1 = nearest: PNG 8/16-bit, EXR, TIFF, NPY")
    src.add_argument("--depth", help="metric depth map in metres: EXR, float TIFF or NPY (as bokehray render reads it)")
    src.add_argument("--depth-model", metavar="DIR", help="no map: estimate one with a local Depth Anything / DPT "
                     "checkpoint folder, as bokehray render --depth-model does (never downloads)")
    v.add_argument("--resize-disparity", action="store_true", help="resize a disparity/depth map of another size")
    v.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; anything else exposes the page to the network)")
    v.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    v.add_argument("--open", action="store_true", help="open the page in the default browser")
    v.add_argument("--export-dir", default=".", help="the only folder exports are written to (default: .)")
    v.add_argument("--proxy-size", type=int, default=640,
                   help="long side in pixels of the live preview (default 640: <= 250 ms per update on 2 cores)")
    v.add_argument("--display-size", type=int, default=2048,
                   help="largest long side of the sharp version rendered for the screen (default 2048; the page asks for "
                   "the size it shows; 100 %% zoom and exports are full size)")
    v.add_argument("--device", default="cpu", help="Warp device: cpu (default), cuda, cuda:N")
    v.add_argument("--debug", action="store_true", help="show tracebacks")
    v.add_argument("--quiet", action="store_true", help="print only the URL and errors")
    return v


def cmd_view(args: argparse.Namespace) -> int:  # noqa: C901
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as e:
        raise InputError(f"bokehray view needs its extra: pip install 'bokehray[view]' ({e})") from None
    from pathlib import Path

    from ..._quiet import init_warp_quietly, native_stderr_quiet
    from .server import ViewServer
    from .session import ViewSession

    if not 0 <= args.port <= 65535:
        raise InputError(f"--port: expected 0 (a free port) or 1..65535, got {args.port}")
    export_dir = Path(args.export_dir)
    if not export_dir.is_dir():
        raise InputError(f"--export-dir {args.export_dir}: not a folder")
    init_warp_quietly(args.debug)  # as `render` does: no native "CUDA driver not found" line on a CPU machine
    import warp as wp

    try:
        with native_stderr_quiet():
            device = str(wp.get_device(args.device))
    except (RuntimeError, ValueError) as e:
        raise InputError(f"--device: {args.device!r} is not available here ({e})") from None
    from ..render_job import RENDER_MODULES, prefetch_imports

    prefetch_imports(RENDER_MODULES)  # the renderer's modules load while the photo is read
    session = ViewSession.from_files(args.image, disparity=args.disparity, depth=args.depth, depth_model=args.depth_model,
                                     resize_disparity=args.resize_disparity, export_dir=export_dir,
                                     proxy_long_side=args.proxy_size, display_long_side=args.display_size,
                                     device=device)
    session.warm_up()  # Warp's modules load before the URL is printed, so the page's first picture comes at once
    server = ViewServer(session, args.host, args.port)
    if args.host not in ("127.0.0.1", "localhost", "::1") and not args.quiet:
        print(f"bokehray view: listening on {args.host}, not only this machine: anyone who can reach it can "
              "render and export", file=sys.stderr)
    # from the printed URL on the server is up: Ctrl-C, SIGTERM and SIGHUP only ask it to stop, wherever they land
    # (ViewServer.stopping_on_signals); a KeyboardInterrupt raised otherwise is still the normal stop
    try:
        with server.stopping_on_signals():
            print(f"bokehray view: {server.url}  ({session.w}x{session.h}, preview {session.proxy_image.shape[1]}x"
                  f"{session.proxy_image.shape[0]}; exports to {session.export_dir}; Ctrl-C stops)", flush=True)
            if not args.quiet:
                s = session.subject
                metres = ""
                if session.norm is not None:
                    near, far = session.depth_range_m()
                    metres = (f"; depth read: {near:.3g} .. {far:.3g} m, the subject "
                              f"{float(session.norm.depth(s.d_f)):.3g} m away")
                print(f"bokehray view: starts as `bokehray render` would: --amount 50 (K = {session.default_k:.1f} px), focus "
                      f"{s.describe()}{', highlights reconstructed' if session.reconstruct_default else ''}{metres}",
                      flush=True)
            if args.open:
                import webbrowser

                webbrowser.open(server.url)
            server.run()
    except KeyboardInterrupt:
        server.stop_signal = server.stop_signal or signal.SIGINT
    finally:
        server.close()
    if not args.quiet:
        with contextlib.suppress(OSError):  # after SIGHUP the terminal may be gone
            print("bokehray view: stopped", file=sys.stderr)
    # stopped by a signal: 128 + its number, as `render` and batches exit (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)
    return 0 if server.stop_signal is None else 128 + int(server.stop_signal)
