"""Regenerate mdcore/data/shear5_measurements.csv exactly (synthetic shear-5 data, seed 0).

Usage, in a checkout: python assets/make_shear5_data.py [--out PATH]

Without ``--out`` it writes the package data file of this checkout (next to this script),
never the copy of an installed mdcore.
"""

import argparse
from pathlib import Path

from mdcore._cases import make_shear5_measurements

CHECKOUT = Path(__file__).resolve().parent.parent
CHECKOUT_CSV = CHECKOUT / "mdcore" / "data" / "shear5_measurements.csv"

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=CHECKOUT_CSV,
                        help=f"where to write the CSV (default: {CHECKOUT_CSV})")
    out = parser.parse_args().out
    out.write_text(make_shear5_measurements(seed=0), encoding="utf-8")
    print(f"wrote {out}")
