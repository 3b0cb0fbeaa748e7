"""The browser viewer (`GET /viewer`) in a real headless Chromium against a real server.

Starts `target/debug/posefuse serve` on the committed bundle, opens `examples/frame.json` in the
page and checks the screenshot: every person's projected keypoints carry that person's colour,
the 3D view is drawn, the console stays clean, and a bad frame shows the API's own error message.
Skipped, with the reason printed, where Chromium, Playwright or the built server is missing.
"""

import io
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "frame.json"
sys.path.insert(0, str(REPO / "clients" / "python" / "tests"))
import live_server  # noqa: E402

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
VIEWPORT = {"width": 1280, "height": 900}  # a laptop's width
COLOUR_TOLERANCE = 8  # per channel, 0..255


def _chromium() -> str | None:
    for path in (os.environ.get("CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if path and Path(path).is_file():
            return path
    return None


def _ort_lib() -> Path:
    return Path(os.environ.get("ORT_DYLIB_PATH", REPO / ".ort" / "lib" / "libonnxruntime.so"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _post(url: str, body: bytes) -> tuple[int, dict]:
    req = urllib.request.Request(url, data=body, headers={"content-type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, json.load(r)
    except urllib.error.HTTPError as e:
        return e.code, json.load(e)


@pytest.fixture(scope="module")
def server():
    """Base URL of a `posefuse serve` on the default bundle, on a free loopback port."""
    if reason := live_server.missing_reason():
        pytest.skip(reason)
    if not _ort_lib().is_file():
        pytest.skip(f"no ONNX Runtime library at {_ort_lib()} (scripts/setup.sh)")
    port = _free_port()
    env = dict(os.environ, ORT_DYLIB_PATH=str(_ort_lib()), RUST_LOG="warn")
    proc = subprocess.Popen(
        [
            str(live_server.binary()),
            "serve",
            "--addr",
            f"127.0.0.1:{port}",
            "--model-dir",
            str(REPO / "models" / "default"),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"{base}/readyz", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None:
                raise RuntimeError(f"posefuse serve exited: {proc.stderr.read().decode(errors='replace')}")
            if time.monotonic() > deadline:
                raise RuntimeError("posefuse serve not ready within 120 s")
            time.sleep(0.2)
        yield base
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """A Playwright context on Debian's Chromium (never a downloaded browser), fresh profile."""
    chromium = _chromium()
    if chromium is None:
        pytest.skip("no Chromium at /usr/bin/chromium (apt-get install chromium)")
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="Playwright is not installed (pip install playwright)"
    )
    with sync_api.sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            str(tmp_path_factory.mktemp("chromium-profile")),
            executable_path=chromium,
            headless=True,
            args=CHROMIUM_FLAGS,
            viewport=VIEWPORT,
            device_scale_factor=1,
        )
        try:
            yield context
        finally:
            context.close()


def _open_page(browser, server):
    page = browser.new_page()
    problems = []
    page.on(
        "console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None
    )
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.goto(f"{server}/viewer")
    page.wait_for_selector("body[data-state=idle]", timeout=30_000)
    return page, problems


def _open_frame(page, path: Path, how: str = "picker"):
    """Opens a file through the file picker or by dropping it on the page; returns the API's JSON
    answer the page received."""
    with page.expect_response(lambda r: r.request.method == "POST" and "/v1/" in r.url) as answer:
        if how == "picker":
            page.set_input_files("#file", str(path))
        else:
            files = page.evaluate_handle(
                """([name, text]) => { const dt = new DataTransfer();
                       dt.items.add(new File([text], name, { type: 'application/json' })); return dt; }""",
                [path.name, path.read_text()],
            )
            page.dispatch_event("main", "drop", {"dataTransfer": files})
    page.wait_for_selector("body[data-state=ready], body[data-state=error]", timeout=60_000)
    return answer.value.json()


def _hex(colour: str) -> tuple[int, int, int]:
    return tuple(int(colour[i : i + 2], 16) for i in (1, 3, 5))


def _close(a, b) -> bool:
    return all(abs(int(x) - int(y)) <= COLOUR_TOLERANCE for x, y in zip(a[:3], b[:3], strict=True))


def test_viewer_draws_every_persons_pose(browser, server, tmp_path):
    image_mod = pytest.importorskip("PIL.Image", reason="Pillow is not installed (pip install pillow)")
    frame = json.loads(EXAMPLE.read_text())
    page, problems = _open_page(browser, server)
    data = _open_frame(page, EXAMPLE)
    assert page.get_attribute("body", "data-state") == "ready", page.inner_text("#error")
    evaluated = any(p.get("ground_truth") for p in frame["persons"])
    response = data["predictions"][0]["response"] if evaluated else data
    assert response["persons"], "the example frame has answered persons"

    shot = tmp_path / "viewer.png"
    page.screenshot(path=str(shot), full_page=True)
    if os.environ.get("POSEFUSE_VIEWER_SCREENSHOT"):
        shutil.copy(shot, os.environ["POSEFUSE_VIEWER_SCREENSHOT"])
    img = image_mod.open(io.BytesIO(shot.read_bytes())).convert("RGB")
    scale = img.width / VIEWPORT["width"]

    # The camera panel: image pixels -> page pixels from the calibration and the canvas's box.
    width, height = frame["calibration"]["width"], frame["calibration"]["height"]
    camera = page.locator("#cameras canvas").first.bounding_box()
    checked = 0
    for person in response["persons"]:
        colour = page.get_attribute(f'#persons li[data-id="{person["id"]}"]', "data-colour")
        assert colour and colour.startswith("#"), person["id"]
        rgb = _hex(colour)
        inside = [
            k["uv"]
            for k in person["keypoints"]
            if k["uv"] and 0 <= k["uv"][0] < width and 0 <= k["uv"][1] < height
        ]
        if not inside:
            continue
        hits = 0
        for u, v in inside:
            x = (camera["x"] + u * camera["width"] / width) * scale
            y = (camera["y"] + v * camera["height"] / height) * scale
            hits += _close(img.getpixel((int(x), int(y))), rgb)
        # Another person's keypoints may cover a few where persons overlap in the image.
        assert hits >= 0.75 * len(inside), f"{person['id']}: {hits} of {len(inside)} keypoints in {colour}"
        checked += 1
    assert checked >= 1, "no person projects into the image"

    # The 3D view is drawn: points and skeletons in the persons' colours on the background.
    box = page.locator("#scene").bounding_box()
    scene = img.crop(
        tuple(int(v * scale) for v in (box["x"], box["y"], box["x"] + box["width"], box["y"] + box["height"]))
    )
    raw = scene.tobytes()
    pixels = [raw[i : i + 3] for i in range(0, len(raw), 3)]
    background = pixels[0]
    drawn = sum(not _close(p, background) for p in pixels)
    assert drawn > 0.005 * len(pixels), f"3D view nearly blank: {drawn} of {len(pixels)} pixels drawn"
    colours = [
        _hex(c) for c in page.eval_on_selector_all("#persons li", "els => els.map(e => e.dataset.colour)")
    ]
    in_colour = sum(any(_close(p, c) for c in colours) for p in pixels)
    assert in_colour > 50, f"only {in_colour} pixels of the 3D view carry a person's colour"

    # Per-person OKS agrees with the server's own metrics (mean over the persons scored in 3D).
    if evaluated:
        oks = [
            float(v)
            for v in page.eval_on_selector_all("#persons li[data-oks]", "els => els.map(e => e.dataset.oks)")
        ]
        report = data["metrics"]["all"]
        assert len(oks) == report["count_3d"]
        assert sum(oks) / len(oks) == pytest.approx(report["mean_oks_3d"], abs=1e-9)

    # Keyboard: the persons list moves the selection and says so to assistive technology.
    page.focus("#persons")
    page.keyboard.press("Home")
    first = page.get_attribute("#persons", "aria-activedescendant")
    assert first == "person-0" and page.get_attribute("#person-0", "aria-selected") == "true"
    if len(response["persons"]) > 1:
        page.keyboard.press("ArrowDown")
        assert page.get_attribute("#persons", "aria-activedescendant") == "person-1"
        assert page.get_attribute("#person-0", "aria-selected") == "false"
        assert response["persons"][1]["id"] in page.inner_text("#detail")
    page.keyboard.press("Escape")
    assert page.get_attribute("#persons", "aria-activedescendant") is None

    # The 3D view turns and zooms from the keyboard.
    before = page.evaluate("document.getElementById('scene').toDataURL()")
    page.focus("#scene")
    page.keyboard.press("ArrowLeft")
    turned = page.evaluate("document.getElementById('scene').toDataURL()")
    page.keyboard.press("+")
    zoomed = page.evaluate("document.getElementById('scene').toDataURL()")
    assert before != turned != zoomed

    # The bundled example opens from the page's own list and gives the same persons.
    with page.expect_response(lambda r: r.request.method == "POST" and "/v1/" in r.url):
        page.select_option("#example", "frame.json")
    page.wait_for_selector("body[data-state=ready]", timeout=60_000)
    ids = page.eval_on_selector_all("#persons li", "els => els.map(e => e.dataset.id)")
    assert ids == [p["id"] for p in response["persons"]]

    assert problems == [], problems


def test_viewer_shows_the_api_error_for_a_bad_frame(browser, server, tmp_path):
    frame = json.loads(EXAMPLE.read_text())
    frame["calibration"]["intrinsic"] = frame["calibration"]["intrinsic"][:8]
    bad = tmp_path / "bad-frame.json"
    bad.write_text(json.dumps(frame))
    not_json = tmp_path / "not-json.json"
    not_json.write_text('{"persons": [oops')
    page, problems = _open_page(browser, server)
    for path, how in ((bad, "picker"), (not_json, "drop")):
        status, body = _post(f"{server}/v1/poses", path.read_bytes())
        assert status in (400, 422), body
        expected = body["error"]
        _open_frame(page, path, how)
        assert page.get_attribute("body", "data-state") == "error", path.name
        assert page.is_visible("#error")
        assert page.inner_text("#error .message") == expected["message"]
        assert page.inner_text("#error code") == expected["code"]
        assert page.locator("#persons li").count() == 0, "a refused frame leaves no person on screen"
    # The browser logs each refused request; nothing else may go wrong.
    assert [p for p in problems if "Failed to load resource" not in p] == [], problems


def test_viewer_stays_usable_with_twenty_persons_at_laptop_width(browser, server, tmp_path):
    frame = json.loads(EXAMPLE.read_text())
    persons = frame["persons"]
    frame["persons"] = [dict(persons[i % len(persons)], id=f"person-{i:02d}") for i in range(20)]
    crowd = tmp_path / "twenty.json"
    crowd.write_text(json.dumps(frame))
    page, problems = _open_page(browser, server)
    data = _open_frame(page, crowd)
    assert page.get_attribute("body", "data-state") == "ready", page.inner_text("#error")
    response = data["predictions"][0]["response"] if "predictions" in data else data
    answered = len(response["persons"])
    assert page.locator("#persons li").count() == answered == 20 - len(response.get("skipped", []))
    # Nothing overflows the laptop-width viewport sideways; the long list scrolls on its own.
    assert page.evaluate("document.documentElement.scrollWidth") <= VIEWPORT["width"]
    assert page.evaluate("(l => l.scrollHeight > l.clientHeight)(document.getElementById('persons'))")
    page.focus("#persons")
    page.keyboard.press("End")
    last = f"person-{answered - 1}"
    assert page.get_attribute("#persons", "aria-activedescendant") == last
    visible = page.evaluate(
        """id => { const l = document.getElementById('persons').getBoundingClientRect();
                   const r = document.getElementById(id).getBoundingClientRect();
                   return r.top >= l.top - 1 && r.bottom <= l.bottom + 1; }""",
        last,
    )
    assert visible, "the selected person is scrolled into view"
    assert response["persons"][-1]["id"] in page.inner_text("#detail")
    closeup_visible = page.evaluate(
        """i => { const c = document.getElementById('closeups').getBoundingClientRect();
                  const r = document.querySelector(`#closeups [data-person="${i}"]`).getBoundingClientRect();
                  return r.left >= c.left - 1 && r.right <= c.right + 1; }""",
        answered - 1,
    )
    assert closeup_visible, "the selected person's close-up is scrolled into view"
    assert problems == [], problems
