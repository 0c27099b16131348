"""What the web viewer costs a browser under a live fleet: tile fetches, bytes, main-thread time, DOM
nodes and JS heap, measured in real headless Chromium against the real service.

    PYTHONPATH=service:clients/python python benchmarks/viewer_cost.py hot      # ~200 scans/s, 4 robots
    PYTHONPATH=service:clients/python python benchmarks/viewer_cost.py fleet    # 100 robots, 2 scans/s

The service runs as a process (tests/service_process.py), the robots as one `fleetmap sim` process
publishing through real Zenoh sessions, and the page is the viewer the service serves, driven by
Playwright. Tile requests are counted with `page.on("request")`, the event stream's bytes (the `data`
of each event the page handles, per event name) by a wrapper of `EventSource.addEventListener`
installed before the page's script runs; main-thread time (`TaskDuration`,
`ScriptDuration`), DOM nodes and JS heap come from CDP's `Performance.getMetrics`, sampled every
`--sample` seconds. One JSON line per sample, then a summary.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from urllib.parse import urlsplit

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))

from service_process import ServiceProcess, wait_for  # noqa: E402

SCENARIOS = {
    # robots, scans per second per robot, beams
    "hot": (4, 50.0, 361),
    "fleet": (100, 2.0, 181),
}
MAP_ID = "viewer-cost"

#: Runs before the viewer's script: counts the characters of every event's data (JSON, so bytes) by
#: event name in `window.__eventBytes`, whatever the stream's URL.
COUNT_EVENTS_JS = """
window.__eventBytes = {};
const addListener = EventSource.prototype.addEventListener;
EventSource.prototype.addEventListener = function (type, listener, options) {
  const counted = function (e) {
    window.__eventBytes[type] = (window.__eventBytes[type] || 0) + (e.data ? e.data.length : 0);
    return listener.call(this, e);
  };
  return addListener.call(this, type, counted, options);
};
"""


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", choices=sorted(SCENARIOS))
    p.add_argument("--robots", type=int, help="override the scenario's robot count")
    p.add_argument("--rate", type=float, help="override the scans per second per robot")
    p.add_argument("--seconds", type=float, default=60.0, help="measured time")
    p.add_argument("--sample", type=float, default=10.0, help="seconds between samples")
    p.add_argument("--hidden", action="store_true", help="measure with the page hidden (visibilityState)")
    p.add_argument("--trace", type=Path, help="also record a Chrome trace of the measured time to this file")
    args = p.parse_args()
    robots, rate, beams = SCENARIOS[args.scenario]
    robots = args.robots or robots
    rate = args.rate or rate

    from playwright.sync_api import sync_playwright
    from test_web_viewer import CHROMIUM, CHROMIUM_ARGS

    with tempfile.TemporaryDirectory() as tmp, ServiceProcess(Path(tmp)) as svc:
        sim = subprocess.Popen(
            [sys.executable, "-m", "fleetmap", "sim", "--robots", str(robots), "--rate", str(rate),
             "--beams", str(beams), "--map", MAP_ID, "--seconds", str(args.seconds + 60),
             "--connect", svc.zenoh_endpoint],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            import httpx

            def robots_seen() -> int:
                r = httpx.get(f"{svc.base_url}/maps/{MAP_ID}")
                return len(r.json()["stats"]["robots"]) if r.status_code == 200 else 0

            wait_for(lambda: robots_seen() >= robots, timeout=120, what="every robot on the map")
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                requests: Counter[str] = Counter()
                page.on(
                    "request",
                    lambda r: requests.update([urlsplit(r.url).path]) if "/tiles/" in r.url else None,
                )
                page.add_init_script(COUNT_EVENTS_JS)
                cdp = page.context.new_cdp_session(page)
                cdp.send("Performance.enable")
                page.goto(f"{svc.base_url}/#map={MAP_ID}")
                page.wait_for_function("() => document.querySelectorAll('.robot-marker').length > 0")
                if args.hidden:
                    page.evaluate(
                        "() => { Object.defineProperty(document, 'visibilityState', {get: () => 'hidden'});"
                        " Object.defineProperty(document, 'hidden', {get: () => true});"
                        " document.dispatchEvent(new Event('visibilitychange')); }"
                    )
                time.sleep(3)  # the first tiles of the fitted view
                requests.clear()
                # The default buffer holds 250 entries: a minute of tiles is more than that.
                page.evaluate(
                    "() => { performance.setResourceTimingBufferSize(1e6);"
                    " performance.clearResourceTimings(); window.__eventBytes = {}; }"
                )
                if args.trace:
                    browser.start_tracing(page=page, categories=TRACE_CATEGORIES)
                start = metrics(cdp)
                t0 = time.monotonic()
                samples = []
                while time.monotonic() - t0 < args.seconds:
                    time.sleep(args.sample)
                    m = metrics(cdp)
                    m["t"] = round(time.monotonic() - t0, 1)
                    m["tile_requests"] = sum(requests.values())
                    samples.append(m)
                    print(json.dumps(m), flush=True)
                elapsed = time.monotonic() - t0
                end = samples[-1]
                if args.trace:
                    args.trace.write_bytes(browser.stop_tracing())
                tile_bytes = page.evaluate(
                    "() => performance.getEntriesByType('resource').filter(e => e.name.includes('/tiles/'))"
                    ".reduce((s, e) => s + e.encodedBodySize, 0)"
                )

                def share(metric: str) -> float:
                    """Percent of the measured time the main thread spent on `metric`."""
                    return round(100 * (end[metric] - start[metric]) / elapsed, 1)

                event_bytes = page.evaluate("() => window.__eventBytes")
                markers = page.evaluate("() => document.querySelectorAll('.robot-marker').length")
                summary = {
                    "scenario": args.scenario, "robots": robots, "rate": rate, "hidden": args.hidden,
                    "seconds": round(elapsed, 1), "markers": markers,
                    "tile_fetches_per_s": round(sum(requests.values()) / elapsed, 1),
                    "tiles_fetched": len(requests),
                    "hottest_tile_fetches_per_s": round(max(requests.values(), default=0) / elapsed, 2),
                    "tile_kbytes_per_s": round(tile_bytes / 1024 / elapsed, 1),
                    "event_kbytes_per_s": round(sum(event_bytes.values()) / 1024 / elapsed, 1),
                    "event_kbytes_per_s_by_name": {
                        name: round(n / 1024 / elapsed, 1) for name, n in sorted(event_bytes.items())
                    },
                    "main_thread_busy_pct": share("TaskDuration"),
                    "script_pct": share("ScriptDuration"),
                    "layout_pct": share("LayoutDuration"),
                    "style_pct": share("RecalcStyleDuration"),
                    "nodes": [start["Nodes"], *(s["Nodes"] for s in samples)],
                    "heap_mb": [round(start["JSHeapUsedSize"] / 2**20, 1),
                                *(round(s["JSHeapUsedSize"] / 2**20, 1) for s in samples)],
                }  # fmt: skip
                if args.trace:
                    summary["main_thread_ms_per_s_by_event"] = main_thread_time(args.trace, elapsed)
                print("SUMMARY " + json.dumps(summary), flush=True)
                browser.close()
        finally:
            sim.terminate()
            sim.wait(30)
    return 0


def metrics(cdp: object) -> dict[str, float]:
    """The CDP performance counters this script reports."""
    wanted = {"TaskDuration", "ScriptDuration", "LayoutDuration", "RecalcStyleDuration", "Nodes",
              "JSHeapUsedSize", "JSEventListeners", "LayoutCount"}  # fmt: skip
    cdp.send("HeapProfiler.collectGarbage")  # type: ignore[attr-defined]  # the heap that stays, not garbage
    got = cdp.send("Performance.getMetrics")["metrics"]  # type: ignore[attr-defined]
    return {m["name"]: m["value"] for m in got if m["name"] in wanted}


#: What a trace records: the renderer's tasks with what they ran (script, style, layout, paint, image
#: decoding); no JS sampling (it would cost the page time itself).
TRACE_CATEGORIES = ["devtools.timeline", "disabled-by-default-devtools.timeline", "blink", "cc"]

#: Trace events worth naming in the summary (they nest: RunTask holds the others).
TRACE_EVENTS = {
    "RunTask", "FunctionCall", "EventDispatch", "TimerFire", "FireAnimationFrame", "V8.Execute",
    "UpdateLayoutTree", "Layout", "PrePaint", "Paint", "Layerize", "UpdateLayer", "Commit",
    "Decode Image", "ImageDecodeTask", "Decode LazyPixelRef", "ParseHTML", "HitTest", "ResourceReceivedData",
}  # fmt: skip


def main_thread_time(trace: Path, seconds: float) -> dict[str, float]:
    """Milliseconds per second the renderer's main thread spent in each of TRACE_EVENTS (complete
    events with a duration; nested events are counted in their parents too), largest first."""
    events = json.loads(trace.read_text())["traceEvents"]
    main = {(e["pid"], e["tid"]) for e in events if e.get("name") == "thread_name"
            and e.get("args", {}).get("name") == "CrRendererMain"}  # fmt: skip
    total: Counter[str] = Counter()
    for e in events:
        if e.get("ph") == "X" and (e["pid"], e["tid"]) in main and e.get("name") in TRACE_EVENTS:
            total[e["name"]] += e.get("dur", 0) / 1000
    return {name: round(ms / seconds, 1) for name, ms in total.most_common()}


if __name__ == "__main__":
    sys.exit(main())
