"""Micro-benchmark: microseconds per seal and per open of a 40-byte body (teleop.session.auth).

What authentication adds to each datagram at 1 kHz.  ``--iterations`` calls of each, timed in
batches of ``--batch``; the figure is the median over batches of the mean per call (a per-call
timer would cost as much as the call).  ``open`` is ``verify`` (header, keyed BLAKE2s tag,
constant-time compare) plus ``accept`` (replay window), on datagrams sealed beforehand with
consecutive counters, as on a lossless link.  CRC-32 of the same body is the baseline: the check
every datagram already had.  Writes JSON (default ``bench/results/auth.json``).

    python -m bench.auth [--out FILE] [--iterations N] [--batch B]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench import write_result
from teleop.session.auth import SESSION, Opener, Sealer, generate_key

BODY = bytes(range(40))


def _per_call_us(run: Callable[[int, int], None], iterations: int, batch: int) -> list[float]:
    """Mean microseconds per call of each batch; ``run(start, n)`` makes calls start..start+n-1."""
    out = []
    for start in range(0, iterations, batch):
        n = min(batch, iterations - start)
        t0 = time.perf_counter_ns()
        run(start, n)
        out.append((time.perf_counter_ns() - t0) / n / 1e3)
    return out


def bench(iterations: int, batch: int) -> dict[str, list[float]]:
    key = generate_key()
    sealer = Sealer(key, SESSION, 0)

    def seal(start: int, n: int) -> None:
        for _ in range(n):
            sealer.seal(BODY)

    sealed = [Sealer(key, SESSION, 0).seal(BODY)]
    s = Sealer(key, SESSION, 0, counter=2)
    sealed += [s.seal(BODY) for _ in range(iterations - 1)]
    verifier, opener = Opener(key, SESSION, 0), Opener(key, SESSION, 0)

    def verify(start: int, n: int) -> None:
        for d in sealed[start : start + n]:
            verifier.verify(d)

    def open_(start: int, n: int) -> None:
        for i, d in enumerate(sealed[start : start + n], start):
            opener.open(d, i * 1e-3)

    def crc(start: int, n: int) -> None:
        for _ in range(n):
            zlib.crc32(BODY)

    return {
        "seal": _per_call_us(seal, iterations, batch),
        "verify": _per_call_us(verify, iterations, batch),
        "open": _per_call_us(open_, iterations, batch),
        "crc32 (baseline)": _per_call_us(crc, iterations, batch),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench/results/auth.json")
    ap.add_argument("--iterations", type=int, default=100_000)
    ap.add_argument("--batch", type=int, default=1000)
    a = ap.parse_args()
    res: dict[str, Any] = {
        "what": "microseconds per call on a 40-byte body, median over batches of the batch mean",
        "body_bytes": len(BODY),
        "iterations": a.iterations,
        "batch": a.batch,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "results": [],
    }
    for part, per_batch in bench(a.iterations, a.batch).items():
        p99 = statistics.quantiles(per_batch, n=100)[98] if len(per_batch) > 1 else per_batch[0]
        med, low = statistics.median(per_batch), min(per_batch)
        res["results"].append({"part": part, "us": med, "p99_batch_us": p99, "min_batch_us": low})
        print(f"{part:<17} {med:6.3f} us  (batch p99 {p99:6.3f}, min {low:6.3f})")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, res)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
