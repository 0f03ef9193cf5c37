"""``python -m fbgforce.contract [--write]``: check the text the runtime contract derives, or
rewrite what is stale (:mod:`fbgforce.contract.render`)."""
from __future__ import annotations

import argparse
import sys

from fbgforce.contract.render import generated_files, stale_files


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.contract",
                                 description="Check or regenerate the C text derived from the "
                                             "runtime contract (fbgforce.contract).")
    ap.add_argument("--write", action="store_true", help="rewrite stale files (default: check)")
    args = ap.parse_args(argv)
    stale = stale_files()
    if args.write:
        for p, t in generated_files().items():
            if p in stale:
                p.write_text(t)
                print(f"wrote {p}")
        return 0
    for p in stale:
        print(f"stale: {p} (run python -m fbgforce.contract --write)", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    raise SystemExit(main())
