#!/usr/bin/env python3
"""Sums the GPU engine's kernel times by kernel, from CubeCL's profiling log.

    CUBECL_DEBUG_LOG=stderr nerf render --run <RUN> --device wgpu --frames 3 2> log.txt
    python3 scripts/kernel_times.py log.txt

CubeCL times each kernel on its own when the log is on (it waits for each one), so the
figures say where the device's time goes, not how fast the engine runs without the log.
A kernel's first launch includes compiling it.
"""
import re
import sys
from collections import defaultdict

UNITS = {"ns": 1e-9, "µs": 1e-6, "us": 1e-6, "ms": 1e-3, "s": 1.0}
LINE = re.compile(r"^\|\s*([0-9.]+)(ns|µs|us|ms|s)\s*\|\s*(\S+?)(?:_[0-9a-f]{8})?\s*$")


def main(path):
    total, count = defaultdict(float), defaultdict(int)
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = LINE.match(line.strip())
            if m:
                seconds = float(m.group(1)) * UNITS[m.group(2)]
                total[m.group(3)] += seconds
                count[m.group(3)] += 1
    if not total:
        sys.exit(f"{path}: no kernel times (was CUBECL_DEBUG_LOG set?)")
    whole = sum(total.values())
    print(f"{'kernel':<28} {'launches':>9} {'seconds':>9} {'share':>6}")
    for name in sorted(total, key=total.get, reverse=True):
        print(f"{name:<28} {count[name]:>9} {total[name]:>9.3f} {total[name] / whole:>6.1%}")
    print(f"{'all':<28} {sum(count.values()):>9} {whole:>9.3f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
