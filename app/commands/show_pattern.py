"""`procam show-pattern`: the calibration pattern fullscreen on a screen, to check a projector set-up
(focus, keystone, that the pattern reaches the corners) before a session."""

from __future__ import annotations

import time

from app.commands import _types
from calib.models.vocab import PatternKind, choices

NAME = "show-pattern"
HELP = "show the projector pattern fullscreen on a screen (Esc or q quits)"
DESCRIPTION = (
    "Opens a fullscreen, pixel-exact window on screen N (see `procam devices`) and shows the circle "
    "grid or chessboard at one pattern position, or cycles through all positions. Esc or q quits."
)


def _size(text: str) -> tuple[int, int]:
    import argparse

    try:
        w, h = text.lower().split("x")
        size = (int(w), int(h))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, e.g. 1920x1080, got '{text}'") from None
    if size[0] <= 0 or size[1] <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got '{text}'")
    return size


def add_arguments(p) -> None:
    p.add_argument("--screen", type=_types.screen, default=None, metavar="N",
                   help="screen index from `procam devices` (default: the non-primary one of two screens; required with more)")
    # the structured-light sequence is not one image at a position: the station shows it (procam session
    # --projector-pattern structured), so it is not offered here
    p.add_argument("--pattern", choices=[k for k in choices(PatternKind) if k != PatternKind.STRUCTURED.value],
                   default=PatternKind.CIRCLES)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--position", type=_types.int_range(0, 999), default=0, metavar="K",
                   help="pattern position (0-based, default 0)")
    g.add_argument("--cycle", type=_types.float_range(0.0, 3600.0, lo_open=True), default=None, metavar="SECONDS",
                   help="show every position in turn, SECONDS each")
    p.add_argument("--size", type=_size, default=None, metavar="WxH",
                   help="image size (default: the screen's); a smaller size opens a borderless window at "
                        "the screen's top-left corner instead of going fullscreen")
    p.add_argument("--cols", type=_types.int_range(2, 200), default=None, help="pattern columns (OpenCV pattern size)")
    p.add_argument("--rows", type=_types.int_range(2, 200), default=None, help="pattern rows")
    p.add_argument("--spacing", type=_types.float_range(0.0, 10000.0, lo_open=True), default=None, metavar="PX",
                   help="point spacing in projector pixels")
    p.add_argument("--positions", type=_types.int_range(1, 999), default=None,
                   help="number of pattern positions (default 13)")
    p.add_argument("--duration", type=_types.float_range(0.0, 86400.0, lo_open=True), default=None, metavar="SECONDS",
                   help="quit by itself after SECONDS (default: wait for Esc or q)")


def run(args) -> int:
    from calib.models.pattern import PatternSpec
    from drivers.errors import DeviceError
    from drivers.projector_window import ProjectorWindow, choose_projector_screen, list_screens, run_projector_loop

    screens = list_screens()
    idx = choose_projector_screen(screens, args.screen)
    screen_size = (screens[idx]["width"], screens[idx]["height"])
    size = args.size or screen_size
    # build the pattern before opening the window so a bad spec fails without flashing a window
    kw = {k: v for k, v in (("cols", args.cols), ("rows", args.rows), ("positions", args.positions)) if v is not None}
    spec = PatternSpec.default_for(size[0], size[1], args.pattern, **kw)
    if args.spacing is not None:
        from dataclasses import replace

        radius = round(0.3 * args.spacing, 1) if spec.kind == PatternKind.CIRCLES else spec.radius_px
        spec = replace(spec, spacing_px=float(args.spacing), radius_px=radius)
    spec.offsets(size[0], size[1])  # raises SpecError when the pattern does not fit
    positions = list(range(spec.positions)) if args.cycle is not None else [args.position]
    for k in positions:
        spec.points_px(size[0], size[1], k)  # range check
    images = {}

    window = ProjectorWindow(idx, size=size, fullscreen=(size == screen_size))
    print(f"screen {idx}: {size[0]}x{size[1]} {spec.kind} {spec.cols}x{spec.rows}, spacing {spec.spacing_px:g} px, "
          f"{spec.positions} positions; Esc or q quits", flush=True)

    def worker():
        t_end = None if args.duration is None else time.monotonic() + args.duration
        i = 0
        while True:
            k = positions[i % len(positions)]
            if k not in images:
                images[k] = spec.render(size[0], size[1], k)[0]
            try:
                window.wait_presented(window.show(images[k]), 5.0)
            except DeviceError:
                if window.closed:  # Esc / q while the image was on its way
                    return 0
                raise
            print(f"showing position {k} ({k + 1} of {spec.positions})", flush=True)
            t_next = None if args.cycle is None else time.monotonic() + args.cycle
            while not window.closed:
                now = time.monotonic()
                if t_end is not None and now >= t_end:
                    return 0
                if t_next is not None and now >= t_next:
                    break
                time.sleep(0.02)
            if window.closed:
                return 0
            i += 1

    return int(run_projector_loop(window, worker) or 0)
