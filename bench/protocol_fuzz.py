"""Fuzz the protocol decoder: 10^5 random and mutated messages must each decode to a valid
message (which must re-encode) or raise ProtocolError from a named check. Anything else is a
bug and fails the run (exit status 1): another exception, a numpy warning, or an error that only
the decoder's safety net caught ("unchecked error").

    .venv/bin/python bench/protocol_fuzz.py [--cases N] [--seed S]
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # runnable from a checkout; tests/support

from protocol import ProtocolError, decode, encode  # noqa: E402
from protocol.codec import UNCHECKED  # noqa: E402
from support.fuzz import mutate, seed_messages  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    warnings.simplefilter("error")  # a warning means a value slipped past validation

    rng = np.random.default_rng(args.seed)
    seeds = seed_messages(rng)
    by_mutation = collections.Counter()  # (mutation, outcome)
    by_field = collections.Counter()  # the field named by each ProtocolError
    crashes = []
    start = time.perf_counter()
    for case in tqdm(range(args.cases), desc="fuzz", unit="case", mininterval=0.5):
        mutation, data = mutate(rng, seeds[case % len(seeds)])
        try:
            message = decode(data)
            decode(encode(message))  # what decodes must also re-encode and decode again
            by_mutation[mutation, "valid"] += 1
        except ProtocolError as error:
            if error.message.startswith(UNCHECKED):
                by_mutation[mutation, "CRASH"] += 1
                crashes.append((mutation, data, str(error)))
                continue
            by_mutation[mutation, "ProtocolError"] += 1
            by_field[error.field] += 1
        except Exception:
            by_mutation[mutation, "CRASH"] += 1
            crashes.append((mutation, data, traceback.format_exc()))
    elapsed = time.perf_counter() - start

    print(
        f"\n{args.cases} cases in {elapsed:.1f} s ({elapsed / args.cases * 1e6:.0f} us per case), "
        f"{len(seeds)} seed messages, seed {args.seed}"
    )
    print(f"{'mutation':<12}{'valid':>10}{'ProtocolError':>15}{'CRASH':>8}")
    for mutation in sorted({m for m, _ in by_mutation}):
        print(
            f"{mutation:<12}"
            + "".join(
                f"{by_mutation[mutation, outcome]:>{width}}"
                for outcome, width in (("valid", 10), ("ProtocolError", 15), ("CRASH", 8))
            )
        )
    totals = collections.Counter()
    for (_, outcome), count in by_mutation.items():
        totals[outcome] += count
    print(f"{'total':<12}{totals['valid']:>10}{totals['ProtocolError']:>15}{totals['CRASH']:>8}")
    print("\nProtocolError by field:")
    for field, count in by_field.most_common():
        print(f"  {count:>7}  {field}")
    for mutation, data, trace in crashes[:5]:
        print(f"\nCRASH after {mutation}, input {data[:64].hex()}...\n{trace}")
    return 1 if crashes else 0


if __name__ == "__main__":
    sys.exit(main())
