"""report.html of a prediction opened in a real browser (headless Chromium): the text is there,
every picture decodes and loads, the before/after slider moves its picture, nothing is fetched
from the network, and on a phone-sized window the page does not overflow sideways. Skipped
with the reason when no Chromium is installed (.ci/setup.sh installs it)."""
import base64
import io
import re
import shutil
import subprocess
from types import SimpleNamespace

import numpy as np
import pytest

from planner.pipeline import Prediction, Progress, write_outputs
from planner.plan import parse_plan

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(n)), None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium/chromium-browser/google-chrome on PATH")

PHONE = (390, 844)

# Appended to a copy of the page: once loaded, count the pictures that failed to decode, move
# the first slider to 20 % and read back its picture's clip, measure the sideways overflow.
CHECK = """<script>
window.addEventListener('load', function () {
  var bad = [];
  for (var i = 0; i < document.images.length; i++) {
    var im = document.images[i];
    if (!(im.complete && im.naturalWidth > 0)) bad.push(im.alt);
  }
  var clip = 'none', r = document.querySelector('.ba input');
  if (r) { r.value = 20; r.dispatchEvent(new Event('input'));
           clip = r.parentNode.querySelector('img.after').style.clipPath; }
  var out = document.createElement('pre'); out.id = 'check';
  out.textContent = 'IMAGES=' + document.images.length + ' BROKEN=' + bad.length +
    ' OVERFLOW=' + (document.documentElement.scrollWidth - window.innerWidth) + ' CLIP=' + clip;
  document.body.appendChild(out);
});
</script>"""


def _block_prediction():
    """A 3 x 2 x 2 block of hexes whose front (+y) is the skin, stretched along y by 0-2 mm,
    with two landmarks: a prediction small enough to render in seconds."""
    nx, ny, nz, h = 3, 2, 2, 10.0
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    nodes = g.reshape(-1, 3).astype(float) * h - [nx * h / 2, 0, 0]
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    hexes = np.array([[idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                       idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]]
                      for i in range(nx) for j in range(ny) for k in range(nz)])
    quads = [[idx[i, ny, k], idx[i, ny, k + 1], idx[i + 1, ny, k + 1], idx[i + 1, ny, k]]
             for i in range(nx) for k in range(nz)]
    front = idx[:, ny, :].ravel()
    model = SimpleNamespace(
        nodes=nodes, hexes=hexes, labels=np.zeros(len(hexes), int), label_names=("dermis",),
        facet_sets={"skin": np.array(quads)}, node_sets={"attach_maxilla": idx[:, 0, :].ravel()},
        regions={"upper_lip": front}, landmarks={"Ls": int(idx[1, ny, 1]), "Pog": int(idx[2, ny, 0])},
        segments=("skull", "maxilla"))
    u = np.zeros_like(nodes)
    u[:, 1] = 0.1 * nodes[:, 1]
    plan = parse_plan({"faceplan": 1, "segments": {"maxilla": {"translation": [0, 2, 0]}}})
    return Prediction(model, plan, u, None, {"converged": True}, {"maxilla": nodes[:4]})


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("browser") / "predict"
    write_outputs(_block_prediction(), out, Progress(echo=False), {"case": "block"})
    return out / "report.html"


def _chromium(*args, timeout=120):
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
           "--hide-scrollbars", "--mute-audio", "--no-first-run", "--disable-extensions",
           f"--window-size={PHONE[0]},{PHONE[1]}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def test_self_contained(report):
    text = report.read_text()
    # every picture is inline and decodes; nothing refers to another file or the network
    srcs = re.findall(r'src="([^"]*)"', text)
    assert len(srcs) >= 10
    for src in srcs:
        assert src.startswith("data:image/"), src[:40]
        base64.b64decode(src.split(",", 1)[1], validate=True)
    assert not re.search(r'(href|src)="(https?:)?//', text)
    assert "<link" not in text and "@import" not in text and "url(" not in text
    assert 'name="viewport"' in text


def test_screenshot_and_dom(report, tmp_path):
    page = tmp_path / "check.html"
    page.write_text(report.read_text().replace("</body>", CHECK + "</body>"))
    dom = _chromium("--virtual-time-budget=20000", "--dump-dom", page.as_uri())
    assert dom.returncode == 0, dom.stderr[-2000:]
    m = re.search(r"IMAGES=(\d+) BROKEN=(\d+) OVERFLOW=(-?\d+) CLIP=([^<]*)<", dom.stdout)
    assert m, dom.stdout[-2000:]
    n_images, broken, overflow, clip = int(m[1]), int(m[2]), int(m[3]), m[4]
    assert n_images >= 10 and broken == 0
    assert overflow <= 0, f"the page is {overflow} px wider than a {PHONE[0]} px phone screen"
    assert "20%" in clip
    for text in ("faceplan prediction", "Before and after", "frontal", "right profile",
                 "submental", "mid-sagittal profile", "turntable", "Landmarks"):
        assert text in dom.stdout, text
    shot = tmp_path / "report.png"
    run = _chromium(f"--screenshot={shot}", "--virtual-time-budget=20000", report.as_uri())
    assert run.returncode == 0 and shot.exists(), run.stderr[-2000:]
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(shot.read_bytes())).convert("L"), float)
    assert img.shape[1] == PHONE[0]
    # a rendered page, not a blank or an error screen: dark text on a light page
    assert img.mean() > 150 and (img < 100).mean() > 0.005
