"""The cohort report in a real browser: headless Chromium opens `report.html` from a small
phantom run, takes a screenshot, and reports every image that failed to decode and any NaN,
Infinity or `undefined` in the text a reader sees. A copy of the page with one broken image
must be caught, so the check can fail.

CI installs Debian's `chromium`; without it here the test is skipped (with CI set it fails).
"""
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from test_heldout import TOY
from test_train_safetensors import BIN

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
PATIENTS = "LIDC-IDRI-0003,LIDC-IDRI-0009"

if CHROMIUM is None:
    if os.environ.get("CI"):
        pytest.fail("chromium is not installed: apt-get install chromium", pytrace=False)
    pytest.skip("no chromium here (apt-get install chromium)", allow_module_level=True)

# Loads the report in a frame of the same folder and writes what it finds into the page,
# which --dump-dom then prints.
CHECKER = """<!DOCTYPE html><html><body><iframe id=r src="{page}" width=1400 height=900></iframe>
<pre id=result>pending</pre><script>
document.getElementById('r').addEventListener('load', () => {{
  const doc = document.getElementById('r').contentDocument;
  const images = [...doc.images];
  const broken = images.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.alt || i.src.slice(0, 40));
  const text = doc.body.innerText;
  const bad = (text.match(/\\bNaN\\b|\\bInfinity\\b|\\bundefined\\b/g) || []);
  document.getElementById('result').textContent = JSON.stringify(
    {{images: images.length, broken: broken, svgs: doc.querySelectorAll('svg').length, bad: bad,
      tables: doc.querySelectorAll('table').length}});
}});
</script></body></html>"""


def chromium(*args, cwd):
    command = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", *args]
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def check(folder: Path, page: str) -> dict:
    (folder / "check.html").write_text(CHECKER.format(page=page))
    dom = chromium("--allow-file-access-from-files", "--virtual-time-budget=20000", "--dump-dom",
                   (folder / "check.html").as_uri(), cwd=folder)
    found = re.search(r'<pre id="result">(.*?)</pre>', dom, re.S)
    assert found and found.group(1) != "pending", dom[-2000:]
    return json.loads(found.group(1).replace("&quot;", '"'))


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    (tmp / "toy.toml").write_text(TOY.format(cohort=REPO / "tools" / "cohorts" / "paper19"))
    done = subprocess.run([BIN, "run", "toy.toml", "--patients", PATIENTS], cwd=tmp, capture_output=True, text=True,
                          env={**os.environ, "CI": "true"})
    assert done.returncode == 0, done.stdout + done.stderr
    return tmp / "out"


def test_the_report_renders_with_every_image_and_no_nan(out):
    found = check(out, "report.html")
    assert found["broken"] == [] and found["bad"] == [], found
    # Two patients' DRR and nodule.png thumbnails, the two plots, and the page's tables.
    assert found["images"] == 4 and found["svgs"] >= 2 and found["tables"] >= 5, found
    shot = out / "report.png"
    chromium(f"--screenshot={shot}", "--window-size=1400,2400", (out / "report.html").as_uri(), cwd=out)
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert pixels.shape == (2400, 1400)
    # A page, not a blank: dark text on white over much of it.
    assert (pixels > 240).mean() > 0.5 and (pixels < 100).mean() > 0.005


def test_a_broken_image_is_caught(out):
    page = (out / "report.html").read_text()
    first = page.index('src="data:image/png;base64,') + len('src="data:image/png;base64,')
    (out / "broken.html").write_text(page[:first] + "AAAA" + page[first + 40:])
    found = check(out, "broken.html")
    assert len(found["broken"]) == 1, found
