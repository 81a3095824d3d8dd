#!/usr/bin/env python3
"""Browser test of omis's web view, in headless Chromium driven over WebDriver (chromedriver).

It starts `omis serve` (loopback, a temporary --data, a client and a worker token, two local
workers) and chromedriver, then, in the browser: answers the token prompt (a wrong token first,
which must be refused), submits a job through the form (a library scene with a finished job as
the reference), watches the preview change, waits for `done`, checks the relMSE chart, the error
map and the workers page, pauses, resumes, reprioritises and cancels a second job from its
page, and saves screenshots under --out (job-page.png is checked not to be blank by decoding
the PNG here).

Python's standard library only: the WebDriver protocol is JSON over HTTP, so no Selenium (and no
driver download) is involved. Every process it starts is stopped on the way out, on failure, on
SIGTERM and on its own deadline.
"""

import argparse
import base64
import json
import os
import secrets
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
import zlib

ELEMENT = "element-6066-11e4-a52e-4f735466cecf"


class Fail(Exception):
    pass


def log(msg):
    print(f"[browser-test {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def wait_for(what, timeout, fn, every=0.1):
    """Calls fn until it returns something truthy; Fail after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    last_err = None
    while time.monotonic() < deadline:
        try:
            v = fn()
            if v:
                return v
        except Fail:
            raise
        except Exception as e:  # a transient WebDriver or HTTP error: try again
            last_err = e
        time.sleep(every)
    raise Fail(f"timed out after {timeout} s waiting for {what}" + (f" (last error: {last_err})" if last_err else ""))


# ---- HTTP ----


def http(method, url, body=None, headers=None, timeout=30):
    data = None
    hdrs = dict(headers or {})
    if body is not None:
        data = json.dumps(body).encode()
        hdrs.setdefault("Content-Type", "application/json")
    req = urllib.request.Request(url, data=data, method=method, headers=hdrs)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


class WebDriver:
    """The few W3C WebDriver commands the test needs."""

    def __init__(self, url):
        self.url = url
        self.session = None

    def call(self, method, path, body=None, timeout=60):
        status, raw = http(method, self.url + path, body if body is not None else ({} if method == "POST" else None), timeout=timeout)
        try:
            v = json.loads(raw or b"{}")
        except ValueError:
            raise Fail(f"WebDriver {method} {path}: HTTP {status}: {raw[:200]!r}")
        value = v.get("value")
        if status >= 400:
            err = value.get("error") if isinstance(value, dict) else value
            msg = value.get("message", "") if isinstance(value, dict) else ""
            raise RuntimeError(f"WebDriver {method} {path}: {err}: {msg.splitlines()[0] if msg else ''}")
        return value

    def start(self, chromium, profile, width, height):
        caps = {
            "capabilities": {
                "alwaysMatch": {
                    "browserName": "chrome",
                    "pageLoadStrategy": "normal",
                    "unhandledPromptBehavior": "ignore",
                    "timeouts": {"script": 30000, "pageLoad": 30000, "implicit": 0},
                    "goog:chromeOptions": {
                        "binary": chromium,
                        "args": [
                            "--headless=new",
                            "--no-sandbox",
                            "--disable-gpu",
                            "--disable-dev-shm-usage",
                            f"--window-size={width},{height}",
                            f"--user-data-dir={profile}",
                            "--no-first-run",
                            "--no-default-browser-check",
                            "--disable-extensions",
                            "--disable-background-networking",
                            "--disable-component-update",
                            "--disable-sync",
                            "--disable-default-apps",
                            "--force-device-scale-factor=1",
                            "--lang=en-US",
                        ],
                    },
                }
            }
        }
        v = self.call("POST", "/session", caps, timeout=90)
        self.session = v["sessionId"]

    def s(self, method, path, body=None):
        return self.call(method, f"/session/{self.session}{path}", body)

    def quit(self):
        if self.session:
            try:
                self.call("DELETE", f"/session/{self.session}", timeout=15)
            except Exception as e:
                log(f"closing the browser session: {e}")
            self.session = None

    def go(self, url):
        self.s("POST", "/url", {"url": url})

    def url_now(self):
        return self.s("GET", "/url")

    def find(self, css):
        """The element for `css`, or None."""
        try:
            return self.s("POST", "/element", {"using": "css selector", "value": css})[ELEMENT]
        except RuntimeError as e:
            if "no such element" in str(e):
                return None
            raise

    def need(self, css, timeout=20):
        return wait_for(f"element {css}", timeout, lambda: self.find(css))

    def click(self, css, timeout=20):
        el = self.need(css, timeout)
        self.s("POST", f"/element/{el}/click")

    def type(self, css, text, clear=True):
        el = self.need(css)
        if clear:
            self.s("POST", f"/element/{el}/clear")
        self.s("POST", f"/element/{el}/value", {"text": text})

    def js(self, script, *args):
        return self.s("POST", "/execute/sync", {"script": script, "args": list(args)})

    def text(self, css):
        # By script: the page re-renders its parts, so element references go stale quickly.
        return self.js("const e = document.querySelector(arguments[0]); return e ? e.innerText : null", css)

    def accept_alert(self):
        self.s("POST", "/alert/accept")

    def screenshot(self):
        return base64.b64decode(self.s("GET", "/screenshot"))


# ---- PNG ----


def decode_png(data):
    """(width, height, channels, rows of bytes) of an 8-bit, non-interlaced PNG."""
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise Fail("the screenshot is not a PNG")
    pos, idat, ihdr = 8, [], None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        chunk = data[pos + 8 : pos + 8 + n]
        pos += 12 + n
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", chunk)
        elif kind == b"IDAT":
            idat.append(chunk)
        elif kind == b"IEND":
            break
    if ihdr is None:
        raise Fail("PNG without IHDR")
    w, hgt, depth, ctype, _, _, interlace = ihdr
    channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(ctype)
    if depth != 8 or channels is None or interlace:
        raise Fail(f"unexpected PNG format: depth {depth}, colour type {ctype}, interlace {interlace}")
    raw = zlib.decompress(b"".join(idat))
    stride = w * channels
    rows, prev = [], bytearray(stride)
    for y in range(hgt):
        f = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        if f == 1:
            for i in range(channels, stride):
                line[i] = (line[i] + line[i - channels]) & 255
        elif f == 2:
            line = bytearray((a + b) & 255 for a, b in zip(line, prev))
        elif f == 3:
            for i in range(stride):
                left = line[i - channels] if i >= channels else 0
                line[i] = (line[i] + ((left + prev[i]) >> 1)) & 255
        elif f == 4:
            for i in range(stride):
                a = line[i - channels] if i >= channels else 0
                b = prev[i]
                c = prev[i - channels] if i >= channels else 0
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        elif f != 0:
            raise Fail(f"bad PNG filter {f}")
        rows.append(line)
        prev = line
    return w, hgt, channels, rows


def check_not_blank(png, what):
    w, hgt, ch, rows = decode_png(png)
    lum, colours = [], set()
    for y in range(0, hgt, 3):
        row = rows[y]
        for x in range(0, w, 3):
            px = row[x * ch : x * ch + min(ch, 3)]
            colours.add(bytes(px))
            lum.append(sum(px) / len(px))
    mean = sum(lum) / len(lum)
    var = sum((v - mean) ** 2 for v in lum) / len(lum)
    log(f"{what}: {w}x{hgt}, luminance mean {mean:.1f}, variance {var:.1f}, {len(colours)} colours")
    if var < 200 or len(colours) < 64:
        raise Fail(f"{what} looks blank: variance {var:.1f}, {len(colours)} colours")


# ---- the test ----

PREVIEW_DIGEST = """
const img = document.getElementById('preview');
if (!img || img.hidden || !img.complete || !img.naturalWidth) return null;
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d');
g.drawImage(img, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data;
let h = 2166136261;
for (let i = 0; i < d.length; i++) { h ^= d[i]; h = Math.imul(h, 16777619) >>> 0; }
return [img.src, img.dataset.pass || '', h];
"""


class Procs:
    def __init__(self):
        self.procs = []

    def start(self, name, argv, **kw):
        log(f"start {name}: {' '.join(argv)}")
        p = subprocess.Popen(argv, start_new_session=True, **kw)
        self.procs.append((name, p))
        return p

    def stop(self, p):
        """Stops one process started here (SIGTERM, then SIGKILL after 15 s)."""
        for i, (name, q) in enumerate(self.procs):
            if q is p:
                del self.procs[i]
                break
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(timeout=15)
            except ProcessLookupError:
                pass
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)

    def stop_all(self):
        for name, p in reversed(self.procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for name, p in reversed(self.procs):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                log(f"{name} did not stop on SIGTERM; killing it")
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(timeout=10)
        self.procs = []


def read_first_line(p, timeout):
    out = {}

    def read():
        out["line"] = p.stdout.readline()

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout)
    return out.get("line")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--omis", default="target/release/omis")
    ap.add_argument("--scenes", default="scenes")
    ap.add_argument("--out", default="target/ci-artefacts")
    ap.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    ap.add_argument("--chromedriver", default=shutil.which("chromedriver") or "/usr/bin/chromedriver")
    ap.add_argument("--scene", default="cornell-box")
    ap.add_argument("--size", type=int, default=96, help="width and height of the test job")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--pass-size", type=int, default=8)
    ap.add_argument("--tile-size", type=int, default=16)
    ap.add_argument("--reference-spp", type=int, default=512)
    ap.add_argument("--deadline", type=float, default=420, help="seconds for the whole test")
    a = ap.parse_args()

    os.makedirs(a.out, exist_ok=True)
    for path, what in [(a.omis, "omis"), (a.chromium, "chromium"), (a.chromedriver, "chromedriver")]:
        if not os.access(path, os.X_OK):
            raise Fail(f"{what} not found at {path}")

    t_start = time.monotonic()
    procs = Procs()
    tmp = tempfile.mkdtemp(prefix="omis-browser-")
    driver = None

    def on_signal(sig, frame):
        raise Fail(f"stopped by signal {sig}")

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGALRM, lambda s, f: (_ for _ in ()).throw(Fail(f"the test ran past its deadline of {a.deadline} s")))
    signal.alarm(int(a.deadline))
    try:
        token = secrets.token_hex(16)
        worker_token = secrets.token_hex(16)
        serve_log = open(os.path.join(a.out, "browser-test-serve.log"), "w")
        env = dict(os.environ, OMIS_LOG="info")
        env.pop("OMIS_TOKEN", None)
        env.pop("OMIS_CLIENT_TOKEN", None)
        env.pop("OMIS_WORKER_TOKEN", None)
        data = os.path.join(tmp, "data")

        def start_serve(bind):
            p = procs.start(
                "omis serve",
                [a.omis, "serve", "--bind", bind, "--data", data, "--workers", "2",
                 "--scenes", a.scenes, "--client-token", token, "--worker-token", worker_token],
                stdout=subprocess.PIPE, stderr=serve_log, text=True, env=env,
            )
            line = read_first_line(p, 30)
            if not line or not line.startswith("listening on "):
                raise Fail(f"omis serve did not start (first line: {line!r}); see {serve_log.name}")
            return p, line.split()[-1].strip()

        serve, base = start_serve("127.0.0.1:0")
        log(f"coordinator at {base}")
        auth = {"Authorization": f"Bearer {token}"}

        def api(method, path, body=None):
            status, raw = http(method, base + path, body, headers=auth)
            if status >= 300:
                raise Fail(f"{method} {path}: HTTP {status}: {raw[:300]!r}")
            return json.loads(raw)

        # The page and its assets need no token; the API does.
        for path in ["/", "/assets/app.js", "/assets/app.css"]:
            status, _ = http("GET", base + path)
            if status != 200:
                raise Fail(f"GET {path} without a token: HTTP {status}")
        status, _ = http("GET", base + "/v1/jobs")
        if status != 401:
            raise Fail(f"GET /v1/jobs without a token: HTTP {status}, want 401")

        # A reference for the relMSE curve, through the API.
        ref = api("POST", "/v1/jobs", {
            "scene": {"library": a.scene}, "name": "reference",
            "settings": {"resolution": [a.size, a.size], "spp": a.reference_spp, "pass_size": a.reference_spp // 4, "tile_size": 32, "seed": 7},
        })
        log(f"reference job {ref['id']} submitted")

        port = free_port()
        cd_log = open(os.path.join(a.out, "browser-test-chromedriver.log"), "w")
        procs.start("chromedriver", [a.chromedriver, f"--port={port}"], stdout=cd_log, stderr=subprocess.STDOUT)
        driver = WebDriver(f"http://127.0.0.1:{port}")
        wait_for("chromedriver", 30, lambda: http("GET", driver.url + "/status", timeout=2)[0] == 200)
        driver.start(a.chromium, os.path.join(tmp, "profile"), 1280, 1150)
        log("browser started")

        wait_for("the reference job", 240, lambda: api("GET", f"/v1/jobs/{ref['id']}")["state"] == "done", every=0.5)
        log(f"reference done after {time.monotonic() - t_start:.1f} s")

        # The page asks for the token on the first 401; a wrong one is refused and asked again.
        driver.go(base + "/")
        wait_for("the token prompt", 20, lambda: driver.js("return document.getElementById('token-dialog').open"))
        driver.type("#token-input", "not-the-token")
        driver.click("#token-form button[type=submit]")
        wait_for("the refusal of a wrong token", 20, lambda: "refused" in (driver.js(
            "const e = document.getElementById('token-error'); return e.hidden ? '' : e.textContent") or ""))
        driver.type("#token-input", token)
        driver.click("#token-form button[type=submit]")
        wait_for("the jobs list", 20, lambda: driver.find(f"#jobs tr[data-id='{ref['id']}']"))
        if driver.js("return document.getElementById('token-dialog').open"):
            raise Fail("the token prompt is still open")
        if token in driver.url_now():
            raise Fail("the token is in the URL")
        if driver.js(f"return sessionStorage.getItem('omis.client-token')") != token:
            raise Fail("the token is not in sessionStorage")
        log("token prompt answered; the jobs list shows the reference")

        # The job form.
        driver.click("a[data-nav=submit]")
        wait_for("the library", 20, lambda: driver.find(f"#f-library option[value='{a.scene}']"))
        driver.js(f"const s = document.getElementById('f-library'); s.value = {json.dumps(a.scene)}; s.dispatchEvent(new Event('change'));")
        driver.type("#f-name", "browser test")
        driver.type("#f-width", str(a.size))
        driver.type("#f-height", str(a.size))
        driver.type("#f-spp", str(a.spp))
        driver.type("#f-pass_size", str(a.pass_size))
        driver.type("#f-tile_size", str(a.tile_size))
        driver.type("#f-seed", "3")
        wait_for("the reference choice", 20, lambda: driver.find(f"#f-refjob option[value='{ref['id']}']"))
        driver.js(f"const s = document.getElementById('f-refjob'); s.value = {json.dumps(ref['id'])}; s.dispatchEvent(new Event('change'));")
        if not driver.js("return document.getElementById('f-ref-job').checked"):
            raise Fail("choosing a reference job did not select 'A finished job'")
        with open(os.path.join(a.out, "form-page.png"), "wb") as f:
            f.write(driver.screenshot())
        driver.click("#f-submit")
        url = wait_for("the job page", 30, lambda: (lambda u: u if "#/jobs/" in u else None)(driver.url_now()))
        job_id = url.split("#/jobs/")[1]
        log(f"job {job_id} submitted through the form")

        # The preview changes while the job runs; the job ends done.
        seen, tiles_seen, states, running_shot = [], set(), [], None
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            d = driver.js(PREVIEW_DIGEST)
            if d and (not seen or seen[-1][2] != d[2]):
                seen.append(d)
                log(f"preview {len(seen)}: pass {d[1]}, digest {d[2]:08x}")
            t = driver.text("#job-state")
            if t and (not states or states[-1] != t):
                states.append(t)
            tiles = driver.text("#job-tiles")
            if tiles and tiles[0] not in "0—":
                tiles_seen.add(tiles)
                if not running_shot and len(seen) >= 3:
                    # The page mid-job: the tiles of the current pass drawn as they finish.
                    running_shot = os.path.join(a.out, "job-page-running.png")
                    with open(running_shot, "wb") as f:
                        f.write(driver.screenshot())
            if t == "done":
                break
            time.sleep(0.1)
        st = api("GET", f"/v1/jobs/{job_id}")
        log(f"states seen: {' -> '.join(states)}; server says {st['state']}, {st['spp_done']} spp, relMSE {st['relmse']}")
        if st["state"] != "done" or "done" not in states:
            raise Fail(f"the job did not reach done in the page (states {states}, server {st['state']})")
        last_pass = st["passes_total"] - 1

        def final_preview():
            d = driver.js(PREVIEW_DIGEST)
            if d and d[1] == str(last_pass):
                if not seen or seen[-1][2] != d[2]:
                    seen.append(d)
                return True
            return False

        wait_for("the preview of the last pass", 30, final_preview)
        distinct = len({d[2] for d in seen})
        log(f"{distinct} distinct previews seen; tiles of a pass seen done: {sorted(tiles_seen)}")
        if distinct < 3:
            raise Fail(f"the preview changed {distinct - 1} times; want at least 2")

        # The relMSE curve, the error map, the downloads.
        wait_for("the relMSE curve", 20, lambda: driver.find("#relmse-chart path.line"))
        npts = driver.js("return document.querySelectorAll('#relmse-chart circle.dot').length")
        if npts < 2:
            raise Fail(f"the relMSE curve has {npts} points")
        wait_for("the error map", 20, lambda: driver.js("const e = document.getElementById('error-map'); return !e.hidden && e.complete && e.naturalWidth > 0"))
        if driver.js("return document.querySelector('button[data-file=\"image.exr\"]').disabled"):
            raise Fail("the EXR download is disabled on a done job")
        if driver.js("return document.querySelectorAll('#events li').length") < st["tiles_per_pass"]:
            raise Fail("the event log misses tile_done events")
        time.sleep(0.5)  # let the last layout settle
        shot = driver.screenshot()
        path = os.path.join(a.out, "job-page.png")
        with open(path, "wb") as f:
            f.write(shot)
        check_not_blank(shot, path)

        # The jobs list and the workers page.
        driver.click("a[data-nav=jobs]")
        wait_for("the job in the list, done", 20, lambda: "done" in (driver.text(f"#jobs tr[data-id='{job_id}']") or ""))
        row = driver.text(f"#jobs tr[data-id='{job_id}']")
        if f"{a.spp} / {a.spp}" not in row:
            raise Fail(f"the jobs list row lacks the spp: {row!r}")
        with open(os.path.join(a.out, "jobs-page.png"), "wb") as f:
            f.write(driver.screenshot())
        driver.click("a[data-nav=workers]")
        wait_for("two workers", 20, lambda: driver.js("return document.querySelectorAll('#workers tbody tr:not(.departed)').length") >= 2)
        with open(os.path.join(a.out, "workers-page.png"), "wb") as f:
            f.write(driver.screenshot())

        # An uploaded scene: a scene file and the mesh it reads, packed into a bundle by the page.
        up = os.path.join(tmp, "upload")
        os.makedirs(up)
        with open(os.path.join(a.scenes, f"{a.scene}.json")) as f:
            scene = json.load(f)
        scene["shapes"].append({"type": "mesh", "file": "wedge.obj", "material": "white"})
        with open(os.path.join(up, "uploaded.json"), "w") as f:
            json.dump(scene, f)
        with open(os.path.join(up, "wedge.obj"), "w") as f:
            f.write("v -0.3 0.9 -0.3\nv 0.3 0.9 -0.3\nv 0 1.4 0.2\nf 1 2 3\n")
        driver.click("a[data-nav=submit]")
        wait_for("the form", 20, lambda: driver.find("#f-files"))
        files = driver.need("#f-files")
        driver.s("POST", f"/element/{files}/value", {"text": os.path.join(up, "uploaded.json") + "\n" + os.path.join(up, "wedge.obj")})
        if not driver.js("return document.getElementById('f-source-upload').checked"):
            raise Fail("choosing files did not select 'Upload'")
        driver.type("#f-width", "32")
        driver.type("#f-height", "32")
        driver.type("#f-spp", "16")
        driver.click("#f-submit")
        url = wait_for("the uploaded job's page", 30, lambda: (lambda u: u if "#/jobs/" in u else None)(driver.url_now()))
        up_id = url.split("#/jobs/")[1]
        wait_for("the uploaded job to be done", 120, lambda: driver.text("#job-state") == "done")
        up_st = api("GET", f"/v1/jobs/{up_id}")
        if up_st["scene"]["main"] != "uploaded.json" or (up_st["width"], up_st["height"]) != (32, 32):
            raise Fail(f"the uploaded job is {up_st['scene']} at {up_st['width']}x{up_st['height']}")
        log("a scene file and its mesh uploaded through the form rendered")

        # A long job: the workers page shows what each worker holds; then cancel from its page.
        long_job = api("POST", "/v1/jobs", {"scene": {"library": a.scene}, "name": "to cancel",
                                            "settings": {"resolution": [a.size, a.size], "spp": 65536, "pass_size": 16}})
        driver.click("a[data-nav=workers]")
        short = long_job["id"][:8]
        wait_for("the workers' current tasks", 30, lambda: f"job {short} pass" in (driver.text("#workers") or ""))
        log("the workers page shows the tasks in hand")
        driver.go(f"{base}/#/jobs/{long_job['id']}")
        event_ids = "return [...document.querySelectorAll('#events li')].map((li) => Number(li.dataset.id))"
        wait_for("the job's events", 30, lambda: len(driver.js(event_ids)) >= 5)

        # The coordinator restarts on the same port and data: the page's event stream breaks, and
        # resumes after the last event it saw (Last-Event-ID), with nothing replayed.
        seen_before = max(driver.js(event_ids))
        procs.stop(serve)
        serve, again = start_serve(base.split("//")[1])
        if again != base:
            raise Fail(f"the coordinator came back at {again}, not {base}")
        log("coordinator restarted under the open job page")
        wait_for("events after the restart", 60, lambda: max(driver.js(event_ids)) > seen_before)
        wait_for("the stream to be live again", 30, lambda: "live" in (driver.text("#live") or ""))
        ids = driver.js(event_ids)
        if any(b >= a_ for a_, b in zip(ids, ids[1:])):
            raise Fail(f"the event log repeats or reorders events after the reconnect: {ids[:40]}")
        log(f"the event stream resumed after event {seen_before} without repeats ({len(ids)} events listed)")
        # Pause and resume from the page; the priority through its prompt.
        wait_for("the pause button", 20, lambda: driver.text("#pause") == "Pause")
        driver.click("#pause")
        wait_for("paused", 20, lambda: driver.text("#job-state") == "paused")
        if driver.text("#job-eta") != "paused" or driver.text("#pause") != "Resume":
            raise Fail(f"a paused job's page shows ETA {driver.text('#job-eta')!r}, button {driver.text('#pause')!r}")
        if api("GET", f"/v1/jobs/{long_job['id']}")["state"] != "paused":
            raise Fail("the server does not say paused")
        driver.click("#pause")
        wait_for("resumed", 20, lambda: driver.text("#job-state") in ("running", "queued"))
        log("pause and resume work")
        driver.click("#priority")
        wait_for("the priority prompt", 10, lambda: driver.s("GET", "/alert/text") is not None)
        driver.s("POST", "/alert/text", {"text": "7"})
        driver.accept_alert()
        wait_for("the new priority", 20, lambda: driver.text("#job-priority") == "7")
        if api("GET", f"/v1/jobs/{long_job['id']}")["priority"] != 7:
            raise Fail("the server does not have the new priority")
        log("the priority is set from the page")
        # The task history on the job page: every attempt so far, with its worker and outcome.
        driver.click("#task-history summary")
        history_rows = "return [...document.querySelectorAll('#task-history tbody tr')].map(r => r.className)"
        wait_for("the task history", 30, lambda: any(c in ("outcome-done", "outcome-running") for c in (driver.js(history_rows) or [])))
        attempts = api("GET", f"/v1/jobs/{long_job['id']}/tasks?limit=200")["attempts"]
        if not attempts:
            raise Fail("the server lists no task attempt of a job the page shows a history of")
        log(f"the task history lists {len(driver.js(history_rows))} attempts")
        wait_for("the cancel button", 20, lambda: driver.js("const b = document.getElementById('cancel'); return b && !b.hidden"))
        driver.click("#cancel")
        wait_for("the confirmation", 10, lambda: driver.s("GET", "/alert/text") is not None)
        driver.accept_alert()
        wait_for("cancelled", 20, lambda: driver.text("#job-state") == "cancelled")
        if api("GET", f"/v1/jobs/{long_job['id']}")["state"] != "cancelled":
            raise Fail("the server does not say cancelled")
        log("cancel works")
        # The jobs list, filtered by state on the server.
        driver.go(base + "/#/jobs")
        wait_for("the jobs list", 20, lambda: long_job["id"] in (driver.js("return document.getElementById('jobs').innerHTML") or ""))
        driver.js("const f = document.getElementById('filter-state'); f.value = 'cancelled'; f.dispatchEvent(new Event('change')); return true")
        row_ids = "return [...document.querySelectorAll('#jobs tbody tr')].map(r => r.dataset.id || '')"
        wait_for("only cancelled jobs listed", 20, lambda: driver.js(row_ids) == [long_job["id"]])
        driver.js("const f = document.getElementById('filter-state'); f.value = 'done'; f.dispatchEvent(new Event('change')); return true")
        wait_for("the cancelled job filtered out", 20, lambda: long_job["id"] not in (driver.js(row_ids) or []))
        log("the jobs list filters by state")

        # A loopback coordinator without tokens: the API answers, so the page never asks.
        open_serve = procs.start(
            "omis serve (no tokens)",
            [a.omis, "serve", "--bind", "127.0.0.1:0", "--data", os.path.join(tmp, "open"), "--scenes", a.scenes],
            stdout=subprocess.PIPE, stderr=serve_log, text=True, env=env,
        )
        line = read_first_line(open_serve, 30)
        if not line or not line.startswith("listening on "):
            raise Fail(f"omis serve without tokens did not start (first line: {line!r})")
        driver.go(line.split()[-1].strip() + "/#/jobs")
        wait_for("the jobs list of the open coordinator", 20, lambda: "No jobs yet" in (driver.text("#jobs") or ""))
        if driver.js("return document.getElementById('token-dialog').open"):
            raise Fail("the page asked for a token of a coordinator that has none")
        log("without tokens on loopback the page works without asking")
        log(f"passed in {time.monotonic() - t_start:.1f} s")
    finally:
        signal.alarm(0)
        if driver:
            driver.quit()
        procs.stop_all()
        shutil.rmtree(tmp, ignore_errors=True)


def free_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


if __name__ == "__main__":
    try:
        main()
    except (Fail, RuntimeError, OSError) as e:
        log(f"FAILED: {e}")
        sys.exit(1)
