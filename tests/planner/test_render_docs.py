"""docs/make_images.py regenerates the README pictures from a prediction's output folder: every
picture is written, the before/after ones are the two renders side by side (pixel for pixel),
the others are the demo's files unchanged; a folder without them is refused (exit 2)."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from planner.pipeline import Progress, write_outputs

ROOT = Path(__file__).resolve().parents[2]


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    # the small block prediction of the browser test (a few seconds to render)
    pred = _load(Path(__file__).parent / "test_report_browser.py", "_browser_case")._block_prediction()
    out = tmp_path_factory.mktemp("demo") / "demo"
    write_outputs(pred, out, Progress(echo=False), {"case": "block"})
    return out


def test_make_images_from_a_prediction(demo, tmp_path):
    from PIL import Image

    mk = _load(ROOT / "docs" / "make_images.py", "make_images")
    out = tmp_path / "images"
    assert mk.main(["--demo", str(demo), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(mk.PICTURES)
    for name, srcs in mk.PICTURES.items():
        if len(srcs) == 1:
            assert (out / name).read_bytes() == (demo / srcs[0]).read_bytes()
            continue
        both = np.asarray(Image.open(out / name).convert("RGB"))
        a = np.asarray(Image.open(demo / srcs[0]).convert("RGB"))
        b = np.asarray(Image.open(demo / srcs[1]).convert("RGB"))
        assert np.array_equal(both[:a.shape[0], :a.shape[1]], a)
        assert np.array_equal(both[:b.shape[0], a.shape[1] + 12:], b)
    assert mk.main(["--demo", str(tmp_path / "nothing"), "--out", str(out)]) == 2
