#!/usr/bin/env python3
"""Summarize a V8 .cpuprofile (tests/browser/e2e.mjs with VOXSTREAM_E2E_CPU_PROFILE=FILE).

    python3 scripts/cpuprofile-summary.py FILE [--top N] [--under NAME]

Prints the functions with the most self time and the most inclusive time (ms), so a long
main-thread task can be split into wasm functions, JS glue and browser work. With --under,
only samples whose stack holds a function whose name contains NAME are counted.
"""
import argparse
import json
from collections import Counter


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("profile")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--under", default=None)
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
    self_ms, incl_ms = Counter(), Counter()
    total = 0.0
    for k, (sample, dt) in enumerate(zip(p["samples"], deltas[1:] + [0])):
        ms = dt / 1000.0
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
    print(f"sampled {total:.1f} ms" + (f" under {a.under!r}" if a.under else ""))
    print("\nself ms")
    for n, ms in self_ms.most_common(a.top):
        print(f"{ms:9.1f}  {n[:120]}")
    print("\ninclusive ms")
    for n, ms in incl_ms.most_common(a.top):
        print(f"{ms:9.1f}  {n[:120]}")


if __name__ == "__main__":
    main()
