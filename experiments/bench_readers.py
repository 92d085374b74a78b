"""Which columnar library parses trajectory CSV / Parquet fastest: pyarrow, pandas or polars.

    python experiments/bench_readers.py            # ≈ 1 min; writes experiments/results/bench_readers.md

Each case runs in a fresh subprocess (so import time and peak memory are the library's own):
read the MarineCadastre AIS columns (MMSI, BaseDateTime, LAT, LON, SOG, COG) of a file into
numpy arrays (int64 ids, datetime64 times, float64 values), as the loader needs them.
pyarrow imports pandas (when installed) at its first conversion to numpy: it runs once as is and
once with pandas hidden, as in an install without pandas. Files: the NY Harbor hour shipped by tracktable-data (8.7k rows), and a 40x copy of it with
shifted MMSIs (348k rows) as CSV and as Parquet, written into a temporary directory.
Figures: median of ``--repeat`` runs (seconds to import the library, seconds to read, peak RSS of
the process: VmHWM).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CASE = r"""
import json, sys, time
def hwm_mb():  # this process's peak RSS (VmHWM: unlike ru_maxrss, not inherited from the parent across exec)
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")) / 1024
start = time.perf_counter()
lib, path = sys.argv[1], sys.argv[2]
cols = ["MMSI", "BaseDateTime", "LAT", "LON", "SOG", "COG"]
import numpy as np
if lib == "pyarrow, no pandas":  # pyarrow imports pandas, when installed, at its first conversion to numpy
    import importlib.abc
    class NoPandas(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] == "pandas":
                raise ImportError("pandas hidden for this case")
    sys.meta_path.insert(0, NoPandas())
    lib = "pyarrow"
if lib == "pyarrow":
    import pyarrow.compute as pc, pyarrow.csv as pcsv, pyarrow.parquet as pq
elif lib == "pandas":
    import pandas as pd
elif lib == "polars":
    import polars as pl
imported = time.perf_counter()
if lib == "pyarrow":
    t = pq.read_table(path, columns=cols) if path.endswith(".parquet") else pcsv.read_csv(
        path, convert_options=pcsv.ConvertOptions(include_columns=cols))
    when = t["BaseDateTime"]
    when = when if str(when.type).startswith("timestamp") else pc.cast(when, "timestamp[s]")
    out = [t["MMSI"].to_numpy(), when.to_numpy()] + [t[c].to_numpy() for c in cols[2:]]
elif lib == "pandas":
    df = pd.read_parquet(path, columns=cols) if path.endswith(".parquet") else pd.read_csv(path, usecols=cols)
    out = [df["MMSI"].to_numpy(), pd.to_datetime(df["BaseDateTime"]).to_numpy()] + [df[c].to_numpy() for c in cols[2:]]
elif lib == "polars":
    df = pl.read_parquet(path, columns=cols) if path.endswith(".parquet") else pl.read_csv(path, columns=cols)
    when = df["BaseDateTime"]
    when = when if when.dtype != pl.String else when.str.to_datetime()
    out = [df["MMSI"].to_numpy(), when.to_numpy()] + [df[c].to_numpy() for c in cols[2:]]
assert len({len(o) for o in out}) == 1 and out[1].dtype.kind == "M"
print(json.dumps({"rows": len(out[0]), "import_s": imported - start, "read_s": time.perf_counter() - imported,
                  "peak_rss_mb": hwm_mb()}))
"""


def run_case(lib: str, path: Path) -> dict[str, float]:
    proc = subprocess.run([sys.executable, "-c", CASE, lib, str(path)], capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def make_files(folder: Path, copies: int) -> list[Path]:
    """The shipped hour, and ``copies`` copies of it (MMSI shifted per copy) as CSV and Parquet."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    from torchsde_lti.data import locate_file

    hour = locate_file("NYHarbor_2020_06_30_first_hour.csv")
    # times stay the file's ISO 8601 strings (every reader parses them itself)
    table = pcsv.read_csv(hour, convert_options=pcsv.ConvertOptions(column_types={"BaseDateTime": pa.string()}))
    parts = [
        table.set_column(
            table.schema.get_field_index("MMSI"),
            "MMSI",
            pc.add(table["MMSI"], pa.scalar(k * 1_000_000_000, pa.int64())),
        )
        for k in range(copies)
    ]
    big = pa.concat_tables(parts)
    csv_path, pq_path = folder / f"ais_x{copies}.csv", folder / f"ais_x{copies}.parquet"
    pcsv.write_csv(big, csv_path)
    pq.write_table(big, pq_path)
    return [hour, csv_path, pq_path]


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--copies", type=int, default=40)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_readers.md"))
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in make_files(Path(tmp), args.copies):
            for lib in ("pyarrow", "pyarrow, no pandas", "pandas", "polars"):
                runs = [run_case(lib, path) for _ in range(args.repeat)]
                rows.append(
                    (
                        path.name,
                        runs[0]["rows"],
                        lib,
                        statistics.median(r["import_s"] for r in runs),
                        statistics.median(r["read_s"] for r in runs),
                        statistics.median(r["peak_rss_mb"] for r in runs),
                    )
                )
                print(rows[-1], flush=True)
    import pandas
    import polars
    import pyarrow

    lines = [
        "# Columnar readers for trajectory files",
        "",
        f"`python experiments/bench_readers.py` (median of {args.repeat} fresh processes; import + read of the "
        f"six AIS columns into numpy; pyarrow {pyarrow.__version__}, pandas {pandas.__version__}, "
        f"polars {polars.__version__}; 2 shared CPU cores).",
        "",
        "| file | rows | library | import (s) | read (s) | peak RSS (MB) |",
        "|---|---:|---|---:|---:|---:|",
    ]
    lines += [f"| {f} | {n} | {lib} | {i:.3f} | {s:.3f} | {m:.0f} |" for f, n, lib, i, s, m in rows]
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
