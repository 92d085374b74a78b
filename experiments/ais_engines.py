"""Which engine moves raw AIS out of core: polars' streaming engine, DuckDB or pyarrow, measured.

    python experiments/ais_engines.py /work/tmp/ais/AIS_2024_01_0[1-3].csv --buckets 64 --threads 2

The job each engine does is the one that needs an engine in ``python -m torchsde_lti.prepare``:
read MarineCadastre CSV files (the six columns the loader uses: MMSI, BaseDateTime as text, LAT,
LON, SOG, COG), add a bucket number (a hash of the MMSI modulo ``--buckets``) and write the rows
as Parquet, one folder per bucket (so that a bucket, ~1/B of the vessels, can later be read
alone). Each engine runs in a fresh process at ``--threads`` threads; the table gives the wall
time, the rows per second and per thread, and the process's peak resident memory (``ru_maxrss``)
on the first file alone and on all of them (memory flat in the data's size or not). Wall time and
peak resident memory are those of the whole process tree, interpreter start included
(:func:`ais_scale.measure`). The machine may be shared: the load before and after each run is
printed beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from ais_scale import measure  # (experiments/ is the script's folder, on sys.path)

COLUMNS = ["MMSI", "BaseDateTime", "LAT", "LON", "SOG", "COG"]


def run_polars(files: list[str], out: str, buckets: int, threads: int) -> int:
    os.environ["POLARS_MAX_THREADS"] = str(threads)
    import polars as pl

    schema = {"MMSI": pl.Int64, "BaseDateTime": pl.String, "LAT": pl.Float64, "LON": pl.Float64}
    schema |= {"SOG": pl.Float64, "COG": pl.Float64}
    lf = pl.scan_csv(files, schema_overrides=schema).select(COLUMNS)
    lf = lf.with_columns(bucket=(pl.col("MMSI").hash(0) % buckets).cast(pl.Int32))
    lf.sink_parquet(pl.PartitionBy(out, key="bucket"), mkdir=True)
    return sum(1 for _ in Path(out).rglob("*.parquet"))


def run_duckdb(files: list[str], out: str, buckets: int, threads: int) -> int:
    import duckdb

    con = duckdb.connect()
    con.execute(f"SET threads = {threads}")
    con.execute("SET memory_limit = '1GB'")
    con.execute("SET preserve_insertion_order = false")
    listed = ", ".join(f"'{f}'" for f in files)
    types = "{'MMSI': 'BIGINT', 'BaseDateTime': 'VARCHAR', 'LAT': 'DOUBLE', 'LON': 'DOUBLE', 'SOG': 'DOUBLE', 'COG': 'DOUBLE'}"
    con.execute(
        f"COPY (SELECT {', '.join(COLUMNS)}, CAST(hash(MMSI) % {buckets} AS INTEGER) AS bucket "
        f"FROM read_csv([{listed}], header = true, types = {types})) "
        f"TO '{out}' (FORMAT parquet, PARTITION_BY (bucket))"
    )
    return sum(1 for _ in Path(out).rglob("*.parquet"))


def run_pyarrow(files: list[str], out: str, buckets: int, threads: int) -> int:
    import numpy as np
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    pa.set_cpu_count(threads)
    pa.set_io_thread_count(threads)
    written = 0
    for i, f in enumerate(files):
        writers: dict[int, pq.ParquetWriter] = {}
        pending: dict[int, list[pa.Table]] = {}
        sizes = dict.fromkeys(range(buckets), 0)
        types = {"MMSI": pa.int64(), "BaseDateTime": pa.string()}
        reader = pcsv.open_csv(
            f,
            read_options=pcsv.ReadOptions(block_size=8 << 20),
            convert_options=pcsv.ConvertOptions(include_columns=COLUMNS, column_types=types),
        )

        def flush(b: int) -> None:
            table = pa.concat_tables(pending.pop(b))
            if b not in writers:
                Path(out, f"bucket={b}").mkdir(parents=True, exist_ok=True)
                writers[b] = pq.ParquetWriter(Path(out, f"bucket={b}", f"part-{i}.parquet"), table.schema)
            writers[b].write_table(table)
            sizes[b] = 0

        for batch in reader:
            mmsi = batch.column("MMSI").to_numpy(zero_copy_only=False).astype(np.uint64)
            bucket = ((mmsi * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(40)) % np.uint64(buckets)
            order = np.argsort(bucket, kind="stable")
            sorted_b = bucket[order]
            table = pa.Table.from_batches([batch]).take(pa.array(order))
            edges = np.flatnonzero(np.diff(sorted_b)) + 1
            for a, z in zip(np.concatenate([[0], edges]), np.concatenate([edges, [len(order)]])):
                b = int(sorted_b[a])
                pending.setdefault(b, []).append(table.slice(int(a), int(z - a)))
                sizes[b] += int(z - a)
                if sizes[b] >= 256_000:
                    flush(b)
        for b in list(pending):
            flush(b)
        for w in writers.values():
            w.close()
        written += len(writers)
    return written


def run_library(files: list[str], out: str, buckets: int, threads: int) -> int:
    """torchsde_lti's scatter: each chunk parsed by ``read_reports`` (pyarrow) then bucketed; one
    process per file (``threads`` processes)."""
    from concurrent.futures import ProcessPoolExecutor

    from torchsde_lti.data import prepare

    tasks = [
        {"path": f, "key": f"f{i}", "out": out, "buckets": buckets, "reading": {}, "chunk_bytes": 32 << 20}
        for i, f in enumerate(files)
    ]
    with ProcessPoolExecutor(threads) as pool:
        entries = list(pool.map(prepare._scatter_file, tasks))
    return sum(len(e["buckets"]) for e in entries)


ENGINES = {"polars": run_polars, "duckdb": run_duckdb, "pyarrow": run_pyarrow, "library": run_library}


def child(engine: str, files: list[str], out: str, buckets: int, threads: int) -> None:
    import resource

    t0 = time.perf_counter()
    n = ENGINES[engine](files, out, buckets, threads)
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MiB (Linux: KiB)
    print(json.dumps({"wall": wall, "rss_mib": rss, "files_written": n}))


def rows_of(files: list[str]) -> int:
    total = 0
    for f in files:
        with open(f, "rb") as fh:
            total += sum(chunk.count(b"\n") for chunk in iter(lambda: fh.read(1 << 24), b"")) - 1
    return total


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("files", nargs="+")
    p.add_argument("--buckets", type=int, default=64)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--engines", default="polars,duckdb,pyarrow,library")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args.child, args.files, args.out, args.buckets, args.threads)
        return
    sizes = {"1 file": args.files[:1], f"{len(args.files)} files": args.files}
    rows = {k: rows_of(v) for k, v in sizes.items()}
    print("| engine | input | rows | wall s | rows/s | rows/s/thread | peak RSS / PSS MiB | load before / after |")
    print("|---|---|---:|---:|---:|---:|---:|---|")
    for _ in range(args.repeat):
        for label, files in sizes.items():
            for engine in args.engines.split(","):
                out = tempfile.mkdtemp(prefix=f"engine-{engine}-", dir=os.environ.get("TMPDIR"))
                cmd = [sys.executable, __file__, *files, "--child", engine, "--out", out]
                cmd += ["--buckets", str(args.buckets), "--threads", str(args.threads)]
                r = measure(cmd)  # wall and peak RSS of the whole process tree (the library's workers too)
                shutil.rmtree(out, ignore_errors=True)
                n = rows[label]
                print(
                    f"| {engine} | {label} | {n:,} | {r['wall']:.1f} | {n / r['wall']:,.0f} | "
                    f"{n / r['wall'] / args.threads:,.0f} | {r['rss_mib']:.0f} / {r['pss_mib']:.0f} | {r['load0']:.1f} / {r['load1']:.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
