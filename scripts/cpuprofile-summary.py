#!/usr/bin/env python3
"""Summarize a V8 .cpuprofile (tests/browser/e2e.mjs with VOXSTREAM_E2E_CPU_PROFILE=FILE).

    python3 scripts/cpuprofile-summary.py FILE [--top N] [--under NAME] [--trace TRACE [--over MS]]

Prints the functions with the most self time and the most inclusive time (ms), so a long
main-thread task can be split into wasm functions, JS glue and browser work. With --under,
only samples whose stack holds a function whose name contains NAME are counted. With --trace (the
same run's VOXSTREAM_E2E_TRACE), only samples inside the streaming main-thread tasks whose thread
time is over --over ms (default 4) are counted: what the long tasks spend. The profile's and the
trace's timestamps are both Chromium's monotonic clock in microseconds.
"""
import argparse
import bisect
import importlib.util
import json
import os
from collections import Counter


def long_task_windows(trace, over_ms):
    """(start, end) in microseconds of the streaming tasks over `over_ms` of thread time, sorted."""
    spec = importlib.util.spec_from_file_location(
        "trace_tasks", os.path.join(os.path.dirname(os.path.abspath(__file__)), "trace-tasks.py")
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    tasks, _, _ = mod.page_tasks(trace, streaming=True)
    return sorted((t["ts"], t["ts"] + t["dur"]) for t in tasks if t.get("tdur", 0) > over_ms * 1000)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("profile")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--under", default=None)
    ap.add_argument("--trace", default=None, help="count only samples inside this trace's long streaming tasks")
    ap.add_argument("--over", type=float, default=4.0, help="with --trace: a long task's thread time, ms")
    a = ap.parse_args()
    p = json.load(open(a.profile))
    nodes = {n["id"]: n for n in p["nodes"]}
    parent = {}
    for n in p["nodes"]:
        for c in n.get("children", []):
            parent[c] = n["id"]

    def name(i):
        f = nodes[i]["callFrame"]
        return f["functionName"] or f"({f['url'].rsplit('/', 1)[-1]}:{f['lineNumber']})"

    deltas = p["timeDeltas"]
    windows = long_task_windows(a.trace, a.over) if a.trace else None
    starts = [w[0] for w in windows] if windows else []
    self_ms, incl_ms = Counter(), Counter()
    total = 0.0
    at = p["startTime"]
    for k, (sample, dt) in enumerate(zip(p["samples"], deltas[1:] + [0])):
        at += deltas[k]
        ms = dt / 1000.0
        if windows is not None:
            w = bisect.bisect_right(starts, at) - 1
            if w < 0 or at > windows[w][1]:
                continue
        stack, i = [], sample
        while i is not None:
            stack.append(name(i))
            i = parent.get(i)
        if a.under and not any(a.under in s for s in stack):
            continue
        if stack[0] in ("(idle)", "(program)", "(garbage collector)") and a.under is None:
            self_ms[stack[0]] += ms
            total += ms
            continue
        total += ms
        self_ms[stack[0]] += ms
        for s in set(stack):
            incl_ms[s] += ms
    where = f" in {len(windows)} streaming tasks over {a.over:g} ms of thread time" if windows is not None else ""
    print(f"sampled {total:.1f} ms" + (f" under {a.under!r}" if a.under else "") + where)
    print("\nself ms")
    for n, ms in self_ms.most_common(a.top):
        print(f"{ms:9.1f}  {n[:120]}")
    print("\ninclusive ms")
    for n, ms in incl_ms.most_common(a.top):
        print(f"{ms:9.1f}  {n[:120]}")


if __name__ == "__main__":
    main()
