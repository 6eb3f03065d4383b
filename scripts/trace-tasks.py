#!/usr/bin/env python3
"""The page's main-thread tasks from a Chromium trace (tests/browser/e2e.mjs with
VOXSTREAM_E2E_TRACE=FILE), by wall time and by thread (CPU) time.

    python3 scripts/trace-tasks.py FILE [--top N] [--json] [--streaming]

A task's wall time counts the time the thread waited (on the GPU process, or off the CPU while
SwiftShader's threads rasterize on the same cores); its thread time is what the main thread
itself ran. Their gap is what the CPU WebGPU adds on a machine with few cores.
"""
import argparse
import json
from collections import Counter


def page_tasks(path, streaming=False):
    """The viewer page's main-thread tasks (RunTask events), the trace's first task time, and a
    function naming what ran in a task. `streaming`: only tasks from the first block a worker
    answered on."""
    events = json.load(open(path))["traceEvents"]
    names = {
        (e["pid"], e["tid"]): e["args"]["name"]
        for e in events
        if e.get("ph") == "M" and e.get("name") == "thread_name"
    }
    # The viewer's renderer: the one whose main thread fires animation frames (Chromium may run
    # another, for the blank page it opened first).
    frames = Counter(
        e["pid"]
        for e in events
        if e.get("name") == "FireAnimationFrame" and names.get((e["pid"], e["tid"])) == "CrRendererMain"
    )
    if not frames:
        raise SystemExit("no animation frame in the trace: was it taken with devtools.timeline?")
    page = frames.most_common(1)[0][0]
    tasks = [
        e
        for e in events
        if e.get("ph") == "X"
        and e.get("name") == "RunTask"
        and e["pid"] == page
        and names.get((e["pid"], e["tid"])) == "CrRendererMain"
    ]
    if not tasks:
        raise SystemExit("no CrRendererMain RunTask events: was the trace taken with devtools.timeline?")
    t0 = min(e["ts"] for e in tasks)
    inner = sorted(
        (
            e
            for e in events
            if e.get("ph") == "X"
            and e["pid"] == page
            and names.get((e["pid"], e["tid"])) == "CrRendererMain"
            and e.get("name") not in ("RunTask", "ThreadControllerImpl::RunTask")
        ),
        key=lambda e: e["ts"],
    )

    def kind(task):
        """What ran in the task: the page-visible events inside it (animation frame, message, ...)."""
        end = task["ts"] + task["dur"]
        seen = []
        for e in inner:
            if e["ts"] < task["ts"]:
                continue
            if e["ts"] > end:
                break
            label = e["name"]
            data = e.get("args", {}).get("data", {})
            if label == "HandlePostMessage":
                label = "message"
            elif label == "EventDispatch":
                label = f"event:{data.get('type')}"
            elif label == "FunctionCall" and data.get("functionName"):
                label = f"call:{data.get('functionName')}"
            if label in ("FireAnimationFrame", "message", "ParseHTML", "EvaluateScript", "TimerFire", "v8.compile",
                         "v8.compileModule", "ResourceReceivedData", "Layout", "UpdateLayoutTree",
                         "v8.wasm.streamFromResponseCallback", "v8.wasm.compiledModule") or label.startswith(("event:", "call:")):
                if label not in seen:
                    seen.append(label)
        return ", ".join(seen[:5])
    # While streaming: from the first block a worker answered (a posted message after the first
    # animation frame, which asks for the first blocks) on.
    first_frame = next((e["ts"] for e in inner if e["name"] == "FireAnimationFrame"), None)
    first_answer = next(
        (e["ts"] for e in inner if e["name"] == "HandlePostMessage" and first_frame is not None and e["ts"] > first_frame),
        None,
    )
    # The harness's own DevTools calls (stopping the trace, the screenshot) run as main-thread tasks too.
    devtools = [
        (e["ts"], e["ts"] + e["dur"])
        for e in inner
        if e["name"] == "Receive mojo message"
        and "DevTools" in json.dumps(e.get("args", {}).get("chrome_mojo_event_info", {}))
    ]
    tasks = [t for t in tasks if not any(t["ts"] <= lo <= t["ts"] + t["dur"] for lo, _ in devtools)]
    if streaming:
        if first_answer is None:
            raise SystemExit("no worker message in the trace: nothing was streamed")
        tasks = [e for e in tasks if e["ts"] + e["dur"] >= first_answer]
    return tasks, t0, kind


def main():
    import signal
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    ap = argparse.ArgumentParser()
    ap.add_argument("trace")
    ap.add_argument("--top", type=int, default=10)
    ap.add_argument("--json", action="store_true", help="print one JSON summary instead")
    ap.add_argument("--streaming", action="store_true", help="only tasks from the first block a worker answered on")
    a = ap.parse_args()
    tasks, t0, kind = page_tasks(a.trace, a.streaming)
    wall = sorted(tasks, key=lambda e: -e["dur"])
    cpu = sorted(tasks, key=lambda e: -e.get("tdur", 0))
    over = lambda key, ms: sum(1 for e in tasks if e.get(key, 0) > ms * 1000)
    summary = {
        "tasks": len(tasks),
        "longestWallMs": wall[0]["dur"] / 1000,
        "longestCpuMs": cpu[0].get("tdur", 0) / 1000,
        "cpuOfLongestWallMs": wall[0].get("tdur", 0) / 1000,
        "tasksOver4msWall": over("dur", 4),
        "tasksOver4msCpu": over("tdur", 4),
        "mainThreadCpuMs": sum(e.get("tdur", 0) for e in tasks) / 1000,
    }
    if a.json:
        print(json.dumps(summary))
        return
    print(json.dumps(summary, indent=1))
    print(f"\nlongest by CPU (thread) time:")
    for e in cpu[: a.top]:
        print(f"  cpu {e.get('tdur', 0) / 1000:7.1f} ms  wall {e['dur'] / 1000:7.1f} ms  at {(e['ts'] - t0) / 1e6:6.2f} s  {kind(e)}")
    print(f"\nlongest by wall time:")
    for e in wall[: a.top]:
        print(f"  wall {e['dur'] / 1000:7.1f} ms  cpu {e.get('tdur', 0) / 1000:7.1f} ms  at {(e['ts'] - t0) / 1e6:6.2f} s  {kind(e)}")


if __name__ == "__main__":
    main()
