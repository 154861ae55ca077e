"""Regenerate the README's pictures (docs/images/) from the outputs of `make demo` (out/demo).

Nothing is rendered or solved here: the pictures are the demo's own, so the README shows what
`make demo` writes. Each before/after picture puts the demo's pre-op and predicted renders of
one view side by side (same camera); the displacement map and the mid-sagittal profile are
copied as they are.

    .venv/bin/python docs/make_images.py [--demo out/demo] [--out docs/images]
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# README picture -> demo picture(s): a pair becomes a side-by-side before/after picture
PICTURES = {
    "demo_frontal.png": ("images/preop_frontal.png", "images/predicted_frontal.png"),
    "demo_profile_before_after.png": ("images/preop_profile.png", "images/predicted_profile.png"),
    "demo_displacement.png": ("images/displacement_three_quarter.png",),
    "demo_profile.png": ("images/profile_midline.png",),
    "demo_turntable.gif": ("images/turntable.gif",),
}


def side_by_side(left: Path, right: Path, path: Path) -> Path:
    """The two pictures next to each other, a 12 px white gap between them."""
    from PIL import Image

    with Image.open(left) as a, Image.open(right) as b:
        a, b = a.convert("RGB"), b.convert("RGB")
        out = Image.new("RGB", (a.width + 12 + b.width, max(a.height, b.height)), "white")
        out.paste(a, (0, 0))
        out.paste(b, (a.width + 12, 0))
        out.save(path, optimize=True)
    return path


def make_images(demo: Path, out: Path) -> list[Path]:
    """Write every README picture from the demo folder `demo` into `out`; return the paths."""
    missing = [p for srcs in PICTURES.values() for p in srcs if not (demo / p).is_file()]
    if missing:
        raise FileNotFoundError(f"{demo} lacks {', '.join(missing)}: run `make demo` first")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, srcs in PICTURES.items():
        if len(srcs) == 2:
            written.append(side_by_side(demo / srcs[0], demo / srcs[1], out / name))
        else:
            written.append(Path(shutil.copyfile(demo / srcs[0], out / name)))
    return written


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, default=ROOT / "out" / "demo", help="the demo's output folder")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images", help="where the pictures go")
    args = ap.parse_args(argv)
    try:
        for p in make_images(args.demo, args.out):
            print(p)
    except FileNotFoundError as exc:
        print(f"make_images: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
