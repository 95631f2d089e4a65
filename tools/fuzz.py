"""Fuzz every byte parser, every emulator's input side and the MAVLink input (run by hand).

    python tools/fuzz.py                      # every target, 1e6 inputs each
    python tools/fuzz.py --n 20000 --targets tk3-driver,dxl-emu
    python tools/fuzz.py --engine random      # without atheris

Engines:

- ``atheris`` (the default when it imports): coverage-guided libFuzzer over the project's
  modules (``drivers``, ``sim_backend``), seeded with valid frames of each protocol;
- ``random``: a mutational fuzzer of our own, seeded with the same frames (bit flips, random
  bytes, inserted/deleted/duplicated ranges, splices of two seeds, the protocols' special bytes,
  plus 10 % purely random inputs); deterministic for a given ``--seed``.

Each target runs in its own process (libFuzzer owns the process it runs in) and reports one
line; the table lists per target the inputs run, the *escapes* (exceptions other than the
documented ones), the *out-of-range* values delivered (see ``tools/fuzz_targets.py`` for what
is checked) and the inputs per second. The first few escaping inputs are written to ``--out``
with their traceback. Exit status 1 if any target escaped or delivered an out-of-range value.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
MAX_LEN = 512
"""Longest input: every frame of these protocols but a big NatNet MODELDEF fits."""
SPECIAL = b"^$\\!#\r=|\xff\x00\x7f\x80\x01\xfe"


def _mutate(rng: random.Random, data: bytes, seeds: list[bytes]) -> bytes:
    """One mutated input from ``data``: 1..8 edits of the kinds libFuzzer uses."""
    buf = bytearray(data)
    for _ in range(rng.randrange(1, 9)):
        op = rng.randrange(8)
        n = len(buf)
        if op == 0 and n:  # flip a bit
            buf[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif op == 1 and n:  # random byte
            buf[rng.randrange(n)] = rng.randrange(256)
        elif op == 2:  # insert random bytes
            pos = rng.randrange(n + 1)
            buf[pos:pos] = rng.randbytes(rng.randrange(1, 9))
        elif op == 3 and n:  # delete a range
            pos = rng.randrange(n)
            del buf[pos:pos + rng.randrange(1, 17)]
        elif op == 4 and n:  # duplicate a range
            pos = rng.randrange(n)
            chunk = buf[pos:pos + rng.randrange(1, 33)]
            at = rng.randrange(len(buf) + 1)
            buf[at:at] = chunk
        elif op == 5:  # splice with another seed
            other = rng.choice(seeds)
            cut_a, cut_b = rng.randrange(n + 1), rng.randrange(len(other) + 1)
            buf = buf[:cut_a] + bytearray(other[cut_b:])
        elif op == 6 and n:  # a protocol's special byte
            buf[rng.randrange(n)] = rng.choice(SPECIAL)
        elif op == 7 and n >= 2:  # an extreme 16- or 32-bit value
            width = rng.choice((2, 4))
            pos = rng.randrange(max(1, n - width + 1))
            value = rng.choice((0, 1, (1 << (8 * width - 1)) - 1, 1 << (8 * width - 1),
                                (1 << (8 * width)) - 1))
            buf[pos:pos + width] = value.to_bytes(width, rng.choice(("big", "little")))
    return bytes(buf[:MAX_LEN])


class _Tally:
    """Counts one target's inputs, escapes and out-of-range values; keeps a few escapes."""

    def __init__(self, name: str, run: Callable[[bytes], int],
                 allowed: tuple[type[BaseException], ...], out: Path) -> None:
        self.name, self.run, self.allowed, self.out = name, run, allowed, out
        self.inputs = self.escapes = self.out_of_range = 0
        self.t0 = time.perf_counter()
        self.kinds: dict[str, int] = {}

    def one(self, data: bytes) -> None:
        self.inputs += 1
        if self.inputs % 20_000 == 0:  # a killed run still leaves its figures
            (self.out / f"{self.name}.progress.json").write_text(
                json.dumps(self.report("partial")))
        try:
            bad = self.run(data)
            if bad and self.out_of_range < 5:
                (self.out / f"{self.name}-out-of-range-{self.out_of_range + 1}.bin"
                 ).write_bytes(data)
            self.out_of_range += bad
        except self.allowed:
            pass
        except Exception as exc:
            self.escapes += 1
            kind = f"{type(exc).__name__}: {str(exc)[:80]}"
            self.kinds[kind] = self.kinds.get(kind, 0) + 1
            if self.escapes <= 5:
                stem = self.out / f"{self.name}-escape-{self.escapes}"
                stem.with_suffix(".bin").write_bytes(data)
                stem.with_suffix(".txt").write_text(traceback.format_exc())

    def report(self, engine: str) -> dict[str, Any]:
        seconds = time.perf_counter() - self.t0
        return {"target": self.name, "engine": engine, "inputs": self.inputs,
                "escapes": self.escapes, "out_of_range": self.out_of_range,
                "seconds": round(seconds, 1),
                "inputs_per_s": round(self.inputs / seconds) if seconds > 0 else 0,
                "escape_kinds": self.kinds}


def _child(name: str, n: int, engine: str, seed: int, out: Path) -> None:
    logging.disable(logging.CRITICAL)  # emulators log every refused input
    sys.path.insert(0, str(HERE))
    if engine == "atheris":
        import atheris  # type: ignore[import-untyped]

        with atheris.instrument_imports(include=["drivers", "sim_backend"]):
            import fuzz_targets
    else:
        import fuzz_targets
    target = fuzz_targets.TARGETS[name]()
    tally = _Tally(name, target.run, target.allowed, out)

    def done() -> None:
        target.close()
        print(json.dumps(tally.report(engine)), flush=True)

    if engine == "atheris":
        corpus = Path(tempfile.mkdtemp(prefix=f"fuzz-{name}-"))
        for i, s in enumerate(target.seeds):
            (corpus / f"seed-{i}").write_bytes(s)

        def one(data: bytes) -> None:
            tally.one(data)
            if tally.inputs >= n:
                # libFuzzer leaves without running atexit handlers: report, then go.
                done()
                os._exit(0)

        # More runs than needed: the count above, not libFuzzer's, ends the run.
        atheris.Setup([sys.argv[0], f"-runs={2 * n + len(target.seeds)}",
                       f"-max_len={MAX_LEN}", f"-seed={seed + 1}", "-rss_limit_mb=4096",
                       str(corpus)], one)
        atheris.Fuzz()
        return
    rng = random.Random(seed)
    seeds = target.seeds
    for s in seeds:
        tally.one(s)
    for _ in range(n - len(seeds)):
        if rng.random() < 0.1:
            tally.one(rng.randbytes(rng.randrange(0, 257)))
        else:
            tally.one(_mutate(rng, rng.choice(seeds), seeds))
    done()


def _engine(requested: str) -> str:
    if requested != "auto":
        return requested
    try:
        import atheris  # noqa: F401
    except ImportError:
        return "random"
    return "atheris"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=float, default=1e6, help="inputs per target [1e6]")
    parser.add_argument("--targets", default="", help="comma-separated names [all]")
    parser.add_argument("--engine", choices=("auto", "atheris", "random"), default="auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="", help="where escaping inputs go [a temp dir]")
    parser.add_argument("--jobs", type=int, default=1, help="targets fuzzed at once [1]")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--child", default="", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    n = int(args.n)
    out = Path(args.out or tempfile.mkdtemp(prefix="fasthex-fuzz-"))
    out.mkdir(parents=True, exist_ok=True)
    engine = _engine(args.engine)
    if args.child:
        _child(args.child, n, engine, args.seed, out)
        return 0

    sys.path.insert(0, str(HERE))
    import fuzz_targets

    names = [t for t in args.targets.split(",") if t] or list(fuzz_targets.TARGETS)
    unknown = [t for t in names if t not in fuzz_targets.TARGETS]
    if unknown:
        parser.error(f"unknown target(s) {unknown}; known: {', '.join(fuzz_targets.TARGETS)}")
    def fuzz_one(name: str) -> dict[str, Any]:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", name, "--n", str(n),
               "--engine", engine, "--seed", str(args.seed), "--out", str(out)]
        with (out / f"{name}.log").open("w") as log:
            proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=log, text=True,
                                  env={**os.environ, "PYTHONHASHSEED": "0"}, check=False)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
        progress = out / f"{name}.progress.json"
        result: dict[str, Any]
        if not lines and progress.exists():
            result = json.loads(progress.read_text())  # engine "partial": the run was cut
        elif not lines:
            result = {
                "target": name, "engine": engine, "inputs": 0, "escapes": 1,
                "out_of_range": 0, "seconds": 0.0, "inputs_per_s": 0,
                "escape_kinds": {f"process exit {proc.returncode}": 1}}
        else:
            result = json.loads(lines[-1])
        print(f"{name}: {result['inputs']} inputs, {result['escapes']} escapes, "
              f"{result['out_of_range']} out of range, {result['inputs_per_s']}/s",
              file=sys.stderr, flush=True)
        return result

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        results = list(pool.map(fuzz_one, names))
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(f"engine: {engine}; escaping inputs and logs in {out}\n")
        print(f"| {'target':22} | {'inputs':>9} | {'escapes':>7} | {'out of range':>12} "
              f"| {'inputs/s':>8} |")
        print(f"|{'-' * 24}|{'-' * 11}:|{'-' * 9}:|{'-' * 14}:|{'-' * 10}:|")
        for r in results:
            print(f"| {r['target']:22} | {r['inputs']:>9} | {r['escapes']:>7} "
                  f"| {r['out_of_range']:>12} | {r['inputs_per_s']:>8} |")
            for kind, count in r["escape_kinds"].items():
                print(f"|   {count} x {kind}")
    bad = any(r["escapes"] or r["out_of_range"] or r["inputs"] < n for r in results)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
