#!/usr/bin/env python3
"""Containers, verified: docker compose runs a coordinator and two workers from the image built
without a registry, and the render service keeps its promises under faults.

  1. `compose up --build`: the coordinator's health check (`omis healthcheck`) turns healthy; the
     web page and its assets are served through the published port without a token, the API
     wants one.
  2. Cut-off worker: a worker holding a task is cut off with `docker network disconnect`; its
     lease expires and the task goes to the other worker; reconnected, its late result is
     refused with 409 (its log and omis_results_refused_total say so) and never merged (no
     tile_done of that worker for that tile); the EXR is bit-identical to `omis render
     --in-process` (`omis diff --layers --eps 0`).
  3. Killed worker: `docker kill` of a worker holding a task mid-job; the job still completes,
     bit-identical.
  4. Restarted coordinator: `compose restart coordinator` mid-job; it resumes on its volume (no
     merged pass lost) and turns healthy again. Drain: `compose stop worker` mid-job; every
     worker logs that it finished and uploaded the tasks in hand and exits 0, and holds no lease;
     started again, they finish the job, bit-identical.

Every compose call uses a project name unique to the run; `down -v` and the removal of the
run's image happen on the way out, on failure, on SIGTERM and at the deadline. Python's standard
library only; the host's release binary is the client (`omis submit`, `download`, `render`,
`diff`).
"""

import argparse
import datetime
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request

T0 = time.monotonic()


class Fail(Exception):
    pass


def log(msg):
    print(f"[compose-test {time.monotonic() - T0:6.1f}s] {msg}", flush=True)


def wait_for(what, timeout, fn, every=0.25):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            v = fn()
            if v:
                return v
        except Fail:
            raise
        except Exception as e:
            last = e
        time.sleep(every)
    raise Fail(f"timed out after {timeout} s waiting for {what}" + (f" (last error: {last})" if last else ""))


def run(argv, timeout=120, check=True, env=None):
    try:
        r = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        raise Fail(f"{' '.join(argv)}: no answer after {timeout} s")
    if check and r.returncode != 0:
        raise Fail(f"{' '.join(argv)}: exit {r.returncode}:\n{r.stdout[-3000:]}")
    return r.stdout


def http(method, url, body=None, headers=None, timeout=15):
    data = json.dumps(body).encode() if body is not None else None
    hdrs = dict(headers or {})
    if data is not None:
        hdrs["Content-Type"] = "application/json"
    req = urllib.request.Request(url, data=data, method=method, headers=hdrs)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def compose_command():
    if subprocess.run(["docker", "compose", "version"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise Fail("neither `docker compose` nor `docker-compose` is installed")


class Stack:
    def __init__(self, a):
        self.a = a
        self.project = f"omis-ci-{os.getpid()}-{secrets.token_hex(3)}"
        self.image = f"omis-ci:{self.project}"
        self.port = free_port()
        self.token = secrets.token_hex(24)
        self.worker_token = secrets.token_hex(24)
        self.base = f"http://127.0.0.1:{self.port}"
        self.dc = compose_command() + ["-p", self.project, "-f", "docker-compose.yml"]
        self.env = dict(
            os.environ,
            OMIS_CLIENT_TOKEN=self.token,
            OMIS_WORKER_TOKEN=self.worker_token,
            OMIS_PORT=f"127.0.0.1:{self.port}",
            OMIS_LEASE_SECONDS=str(a.lease),
            OMIS_WORKER_THREADS="1",
            OMIS_BUILD_TARGET="prebuilt",
            OMIS_RUNTIME_IMAGE=a.base_image,
            OMIS_IMAGE=self.image,
            OMIS_LOG="info",
        )
        self.up = False

    def compose(self, *args, timeout=180, check=True):
        return run(self.dc + list(args), timeout=timeout, check=check, env=self.env)

    def api(self, method, path, body=None):
        status, raw = http(method, self.base + path, body, headers={"Authorization": f"Bearer {self.token}"})
        if status >= 300:
            raise Fail(f"{method} {path}: HTTP {status}: {raw[:300]!r}")
        return json.loads(raw)

    def metric(self, name):
        status, raw = http("GET", self.base + "/metrics")
        if status != 200:
            raise Fail(f"/metrics: HTTP {status}")
        for line in raw.decode().splitlines():
            if line.startswith(name + " ") or line.startswith(name + "{"):
                return float(line.split()[-1])
        return 0.0

    def containers(self, service):
        return self.compose("ps", "-q", service).split()

    def inspect(self, cid, fmt):
        return run(["docker", "inspect", "-f", fmt, cid], timeout=30).strip()

    def health(self):
        cids = self.containers("coordinator")
        return self.inspect(cids[0], "{{.State.Health.Status}}") if cids else "absent"

    def wait_healthy(self, timeout=90):
        t = time.monotonic()
        wait_for("the coordinator's health check to say healthy", timeout, lambda: self.health() == "healthy", every=0.5)
        log(f"coordinator healthy ({time.monotonic() - t:.1f} s)")

    def worker_map(self):
        """Registered, live workers of this stack by container id: {cid: worker}."""
        by_host = {}
        for cid in self.containers("worker"):
            by_host[self.inspect(cid, "{{.Config.Hostname}}")] = cid
        out = {}
        for w in self.api("GET", "/v1/workers")["workers"]:
            host = w["name"].rsplit("-", 1)[0]
            if w["state"] in ("idle", "busy") and host in by_host:
                out[by_host[host]] = w
        return out

    def logs(self, cid, since=None):
        argv = ["docker", "logs"] + (["--since", since] if since else []) + [cid]
        return run(argv, timeout=30, check=False)

    def network_of(self, cid):
        nets = json.loads(self.inspect(cid, "{{json .NetworkSettings.Networks}}"))
        if len(nets) != 1:
            raise Fail(f"container {cid[:12]} is on networks {list(nets)}; want one")
        return next(iter(nets))


def job_flags(s):
    return ["--resolution", f"{s['size']}x{s['size']}", "--spp", str(s["spp"]), "--pass-size", str(s["pass_size"]),
            "--tile-size", str(s["tile_size"]), "--seed", str(s["seed"])]


def submit(st, omis, s):
    """Submits through the omis CLI and the published port; returns the job id."""
    out = run([omis, "submit", "cornell-box", *job_flags(s), "--name", s["name"], "--server", st.base, "--client-token", st.token], timeout=60)
    job = out.strip().splitlines()[-1].strip()
    if not re.fullmatch(r"[0-9a-f-]{36}", job):
        raise Fail(f"omis submit printed {out!r}")
    log(f"job {s['name']} ({job[:8]}) submitted: {s['size']}x{s['size']}, {s['spp']} spp in passes of {s['pass_size']}")
    return job


def events_of(st, job):
    """The event log of an ended job (the stream ends after it)."""
    status, raw = http("GET", f"{st.base}/v1/jobs/{job}/events", headers={"Authorization": f"Bearer {st.token}"}, timeout=30)
    if status != 200:
        raise Fail(f"events of {job}: HTTP {status}")
    out, kind = [], None
    for line in raw.decode().splitlines():
        if line.startswith("event:"):
            kind = line[6:].strip()
        elif line.startswith("data:") and kind:
            out.append((kind, json.loads(line[5:].strip())))
            kind = None
    return out


def wait_done(st, a, job, name):
    def done():
        j = st.api("GET", f"/v1/jobs/{job}")
        if j["state"] in ("failed", "cancelled"):
            raise Fail(f"job {name}: {j['state']}: {j['error']}")
        return j["state"] == "done"

    wait_for(f"job {name} to be done", a.job_timeout, done, every=0.5)


def check_image(st, a, job, s, tmp):
    """The job's EXR, downloaded through the published port, equals an in-process render."""
    wait_done(st, a, job, s["name"])
    got = os.path.join(tmp, f"{s['name']}-service.exr")
    want = os.path.join(tmp, f"{s['name']}-in-process.exr")
    run([a.omis, "download", job, "--out", got, "--server", st.base, "--client-token", st.token], timeout=60)
    run([a.omis, "render", os.path.join(a.scenes, "cornell-box.json"), "--in-process", *job_flags(s), "--out", want], timeout=600)
    r = subprocess.run([a.omis, "diff", got, want, "--layers", "--eps", "0"], stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True, timeout=60)
    if r.returncode != 0:
        raise Fail(f"job {s['name']}: the service's EXR differs from the in-process render:\n{r.stdout}")
    log(f"job {s['name']}: the EXR is bit-identical to omis render --in-process")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--omis", default="target/release/omis")
    ap.add_argument("--scenes", default="scenes")
    ap.add_argument("--out", default="target/ci-artefacts")
    ap.add_argument("--base-image", default="omis-base:bookworm")
    ap.add_argument("--lease", type=float, default=20, help="--lease-seconds of the coordinator")
    ap.add_argument("--job-timeout", type=float, default=240)
    ap.add_argument("--deadline", type=float, default=540)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)

    st = Stack(a)
    tmp = tempfile.mkdtemp(prefix="omis-compose-")

    def on_signal(sig, frame):
        raise Fail(f"stopped by signal {sig}")

    def on_alarm(sig, frame):
        raise Fail(f"the test ran past its deadline of {a.deadline} s")

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(int(a.deadline))
    try:
        log(f"project {st.project}, {' '.join(compose_command())}, image {st.image} on {a.base_image}, port {st.port}")
        st.up = True
        t = time.monotonic()
        try:
            st.compose("up", "-d", "--build", "--scale", "worker=2", timeout=300)
        except Fail as e:
            # A BuildKit set up with a builder that cannot see local images (a docker-container
            # driver) cannot use the local base image; the classic builder can.
            log(f"compose up --build failed; again with the classic builder (DOCKER_BUILDKIT=0): {e}")
            st.env["DOCKER_BUILDKIT"] = "0"
            st.compose("up", "-d", "--build", "--scale", "worker=2", timeout=300)
        log(f"compose up --build (the prebuilt target on {a.base_image}): {time.monotonic() - t:.1f} s")

        # 1. Health check, the page, the token.
        st.wait_healthy()
        run([a.omis, "healthcheck", "--server", st.base], timeout=30)
        status, page = http("GET", st.base + "/")
        if status != 200 or b"/assets/app.js" not in page:
            raise Fail(f"GET / through the published port: HTTP {status}")
        for path in ["/assets/app.js", "/assets/app.css"]:
            if http("GET", st.base + path)[0] != 200:
                raise Fail(f"GET {path}: not served")
        if http("GET", st.base + "/v1/jobs")[0] != 401:
            raise Fail("the API answers without a token")
        log("the web page is served without a token; the API wants one")
        wait_for("two workers", 60, lambda: len(st.worker_map()) == 2)
        log("two workers registered")

        # 2. A worker cut off from the network: its late result is refused, never merged.
        #    Tasks of 32 x 32 pixels x 128 spp: the worker spends its hold rendering, so the cut
        #    almost never lands in the few milliseconds of an upload (a request cut mid-flight
        #    ends only when the worker's TCP timeouts notice, about 10 s later, and a heartbeat
        #    after the reconnection may then tell it the task is gone before the 409 path runs).
        s2 = dict(name="cutoff", size=128, spp=512, pass_size=128, tile_size=32, seed=11)
        job2 = submit(st, a.omis, s2)
        refused0 = st.metric("omis_results_refused_total")
        expired0 = st.metric("omis_leases_expired_total")
        cut, task = None, None
        for attempt in range(10):
            cid, w = wait_for("a worker holding a task of the job", 60, lambda: next(
                ((c, w) for c, w in st.worker_map().items() if any(t["job_id"] == job2 for t in w["tasks"])), None), every=0.1)
            net = st.network_of(cid)
            run(["docker", "network", "disconnect", net, cid], timeout=30)
            cut_at = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime())
            # What the coordinator thinks the cut-off worker holds now is its late result.
            w = next(x for x in st.api("GET", "/v1/workers")["workers"] if x["id"] == w["id"])
            held = [t for t in w["tasks"] if t["job_id"] == job2]
            if held:
                cut, task = (cid, w, net), held[0]
                break
            run(["docker", "network", "connect", net, cid], timeout=30)
            log("the worker finished its task before the cut; again")
            time.sleep(0.5)
        if not cut:
            raise Fail("could not cut off a worker while it held a task")
        cid, w, net = cut
        log(f"worker {w['name']} cut off holding task {task['id']} (pass {task['pass']} tile {task['tile']} attempt {task['attempt']})")
        wait_for("the cut-off worker's lease to expire", a.lease * 3 + 30,
                 lambda: st.metric("omis_leases_expired_total") > expired0, every=0.5)
        log("its lease expired")
        wait_for("the task to be taken by the other worker", 60, lambda: any(
            t["id"] == task["id"] for x in st.api("GET", "/v1/workers")["workers"] if x["id"] != w["id"] for t in x["tasks"])
            or st.api("GET", f"/v1/jobs/{job2}")["passes_done"] > task["pass"], every=0.2)
        # Reconnect at a moment when the upload's retry must come before the next heartbeat
        # (which would tell the worker that the task is no longer its own, so that it drops the
        # result instead of sending it). Cut off, each attempt of either hangs for the worker's
        # 5 s connect timeout; the upload then sleeps 3 s (from its 5th failure on), the
        # heartbeat a quarter lease (5 s). So just after a failed heartbeat that came at most 2 s
        # after a failed upload, the upload's next attempt starts within 1-3 s, connected, and
        # the heartbeat's in 5 s. The two cycles (8 s, 10 s) drift by 2 s a round, so such a
        # moment comes within a few rounds.
        stamp = re.compile(r"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{1,6})\d*Z")

        def failures(text, what):
            return [datetime.datetime.fromisoformat(m.group(1)) for line in text.splitlines()
                    if what in line for m in [stamp.search(line)] if m]

        seen = [len(failures(st.logs(cid, cut_at), "heartbeat:"))]

        def moment():
            text = st.logs(cid, cut_at)
            beats, ups = failures(text, "heartbeat:"), failures(text, f"upload of task {task['id']}:")
            if len(beats) == seen[0]:
                return False
            seen[0] = len(beats)
            before = [u for u in ups if u <= beats[-1]]
            return len(before) >= 5 and (beats[-1] - before[-1]).total_seconds() <= 2.0

        wait_for("a failed heartbeat just after a failed upload", 120, moment, every=0.1)
        run(["docker", "network", "connect", net, cid], timeout=30)
        log("reconnected between a failed upload's retry and the next heartbeat")
        refusal = f"task {task['id']} (job {job2} pass {task['pass']} tile {task['tile']}) refused: HTTP 409"

        def refused():
            text = st.logs(cid, cut_at)
            if f"task {task['id']} was taken back; result dropped" in text:
                raise Fail("a heartbeat told the worker that the task was gone before its upload retried, "
                           "so the 409 path was not exercised (timing; see target/ci-artefacts/compose-test.log)")
            return refusal in text

        wait_for("the late result to be refused with 409", 60, refused, every=0.3)
        refused = st.metric("omis_results_refused_total")
        if refused <= refused0:
            raise Fail(f"omis_results_refused_total did not grow ({refused0} -> {refused})")
        log(f"late result refused with 409 (omis_results_refused_total {refused0:.0f} -> {refused:.0f})")
        check_image(st, a, job2, s2, tmp)
        merged = [d for k, d in events_of(st, job2) if k == "tile_done" and d["pass"] == task["pass"] and d["tile"] == task["tile"]]
        if len(merged) != 1 or merged[0]["worker"] == w["id"]:
            raise Fail(f"tile_done events of pass {task['pass']} tile {task['tile']}: {merged}")
        log("the refused result was never merged (the tile's one tile_done is the other worker's)")

        # 3. A worker killed mid-job. Tasks of 64 x 64 pixels x 32 spp (a few tenths of a second):
        #    a worker seen holding a task can still finish it before `docker kill` lands, so the
        #    coordinator's view right after the kill decides whether a lease was cut; if not, the
        #    worker is started again and killed again.
        s3 = dict(name="kill", size=128, spp=256, pass_size=32, tile_size=64, seed=5)
        job3 = submit(st, a.omis, s3)
        wait_for("a live second worker", 60, lambda: len(st.worker_map()) == 2)
        expired0 = st.metric("omis_leases_expired_total")
        for attempt in range(5):
            cid, w = wait_for("a worker holding a task of the job", 60, lambda: next(
                ((c, w) for c, w in st.worker_map().items() if any(t["job_id"] == job3 for t in w["tasks"])), None),
                every=0.05)
            run(["docker", "kill", cid], timeout=30)
            held = [t for x in st.api("GET", "/v1/workers")["workers"] if x["id"] == w["id"]
                    for t in x["tasks"] if t["job_id"] == job3]
            if held:
                break
            log(f"worker {w['name']} finished its task before the kill landed; starting it to kill again")
            run(["docker", "start", cid], timeout=60)
        else:
            raise Fail("five kills all landed between two tasks")
        j = st.api("GET", f"/v1/jobs/{job3}")
        if j["state"] != "running":
            raise Fail(f"the job is {j['state']} at the kill; want running (mid-job)")
        log(f"killed worker {w['name']} mid-job holding {len(held)} task(s) (pass {j['passes_done']} of {j['passes_total']} merged)")
        wait_for("the killed worker's lease to expire", a.lease * 3 + 30, lambda: st.metric("omis_leases_expired_total") > expired0, every=0.5)
        log("its lease expired; the task is requeued")
        check_image(st, a, job3, s3, tmp)
        if st.inspect(cid, "{{.State.Running}}") != "true":
            run(["docker", "start", cid], timeout=60)

        # 4. The coordinator restarted on its volume mid-job, then the workers drained mid-job
        #    (right after, so that the job is mid-way on any machine), then started again.
        s4 = dict(name="restart", size=128, spp=1024, pass_size=16, tile_size=32, seed=9)
        job4 = submit(st, a.omis, s4)
        wait_for("a pass merged", 120, lambda: st.api("GET", f"/v1/jobs/{job4}")["passes_done"] >= 1, every=0.1)
        before = st.api("GET", f"/v1/jobs/{job4}")
        st.compose("restart", "-t", "20", "coordinator", timeout=120)
        log(f"coordinator restarted mid-job (pass {before['passes_done']} of {before['passes_total']} merged before)")
        wait_for("the coordinator to answer", 60, lambda: http("GET", st.base + "/healthz", timeout=2)[0] == 200, every=0.1)
        workers = st.containers("worker")
        since = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(time.time() - 1))
        st.compose("stop", "-t", "120", "worker", timeout=180)
        uploaded = 0
        for c in workers:
            text = st.logs(c, since)
            code = st.inspect(c, "{{.State.ExitCode}}")
            m = re.search(r"drained: (\d+) task result\(s\) finished and uploaded since the signal", text)
            if "draining: finishing the" not in text or not m or code != "0":
                raise Fail(f"worker {c[:12]} did not drain (exit {code}):\n{text[-2000:]}")
            uploaded += int(m.group(1))
        held = [w for w in st.api("GET", "/v1/workers")["workers"] if w["tasks"]]
        if held:
            raise Fail(f"workers still hold leases after the drain: {held}")
        j = st.api("GET", f"/v1/jobs/{job4}")
        log(f"compose stop worker: both drained (exit 0), {uploaded} task result(s) uploaded after SIGTERM; "
            f"the job is {j['state']} at pass {j['passes_done']} of {j['passes_total']}")
        if j["state"] != "running":
            raise Fail(f"the job is {j['state']} after the drain; want running (mid-job)")
        if uploaded < 1:
            raise Fail("no worker held a task when stopped; the drain was not exercised")
        if j["passes_done"] < before["passes_done"]:
            raise Fail(f"the restart lost merged passes ({before['passes_done']} -> {j['passes_done']})")
        st.wait_healthy()
        st.compose("start", "worker", timeout=120)
        check_image(st, a, job4, s4, tmp)
        log(f"passed in {time.monotonic() - T0:.1f} s")
    finally:
        signal.alarm(0)
        if st.up:
            try:
                with open(os.path.join(a.out, "compose-test.log"), "w") as f:
                    f.write(st.compose("logs", "--no-color", "-t", timeout=60, check=False))
            except Exception as e:
                log(f"saving the logs: {e}")
            st.compose("down", "-v", "--remove-orphans", "-t", "10", timeout=180, check=False)
            run(["docker", "image", "rm", "-f", st.image], timeout=60, check=False)
            log(f"stopped and removed project {st.project}")
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    try:
        main()
    except (Fail, OSError) as e:
        log(f"FAILED: {e}")
        sys.exit(1)
