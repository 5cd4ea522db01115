"""Regenerate assets/shear5_measurements.csv exactly (synthetic shear-5 data, seed 0).

Usage: python assets/make_shear5_data.py
"""

from mdcore.cases import SHEAR5_CSV, make_shear5_measurements

if __name__ == "__main__":
    SHEAR5_CSV.write_text(make_shear5_measurements(seed=0), encoding="utf-8")
    print(f"wrote {SHEAR5_CSV}")
