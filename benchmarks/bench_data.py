"""Load + label time and peak memory for a generated DSRL-sized dataset (3 M transitions, obs dim 34).

    make bench                                      # runs this after the loss benchmark
    python benchmarks/bench_data.py --transitions 3000000 --obs-dim 34 --act-dim 8 [--compression gzip]

A file with the DSRL layout is written once into a temporary folder (chunk by chunk), then each measurement runs
in a fresh Python process so that its peak resident memory (ru_maxrss) is its own: the printed "extra" memory
is the peak minus the process's memory after imports, and the ratio divides it by the size of the arrays held
(observations, next observations, actions, rewards, costs, flags as loaded). A ratio near 1 means the data
were copied into memory once. Peak RSS also counts the page cache of memory-mapped files, so for the
memory-mapped variant the telling number is the anonymous memory kept (RssAnon): what could not be paged out.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

CHILD = r"""
import json, resource, sys, time
import torch
from spoil_torchrl.data import load_episodes, episode_stats, label_ilsp
torch.set_num_threads(2)
path, memmap_dir = sys.argv[1], (sys.argv[2] or None)
def anon_mib():
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
base_anon = anon_mib()
t0 = time.perf_counter()
episodes = load_episodes(f"file:{path}", memmap_dir=memmap_dir)
t1 = time.perf_counter()
stats = episode_stats(episodes)
labels = label_ilsp(stats, cost_threshold=40.0)
t2 = time.perf_counter()
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
held = sum(v.numel() * v.element_size() for v in episodes.values(True, True))
print(json.dumps({"load_s": t1 - t0, "label_s": t2 - t1, "extra_mib": (peak - base) / 1024,
                  "anon_mib": anon_mib() - base_anon,
                  "held_mib": held / 2**20, "n": episodes.shape[0], "episodes": stats.shape[0],
                  "safe": len(labels["safe"]), "performant": len(labels["performant"])}))
"""


def write_dataset(
    path: Path, n: int, obs_dim: int, act_dim: int, episode_length: int, compression: str | None
):
    rng = np.random.default_rng(0)
    chunk = 100_000
    with h5py.File(path, "w") as f:
        dsets = {
            "observations": f.create_dataset("observations", (n, obs_dim), "f4", compression=compression),
            "next_observations": f.create_dataset(
                "next_observations", (n, obs_dim), "f4", compression=compression
            ),
            "actions": f.create_dataset("actions", (n, act_dim), "f4", compression=compression),
            "rewards": f.create_dataset("rewards", (n,), "f4", compression=compression),
            "costs": f.create_dataset("costs", (n,), "f4", compression=compression),
            "terminals": f.create_dataset("terminals", (n,), "f4", compression=compression),
            "timeouts": f.create_dataset("timeouts", (n,), "f4", compression=compression),
        }
        for start in range(0, n, chunk):
            stop = min(start + chunk, n)
            rows = np.arange(start, stop)
            dsets["observations"][start:stop] = rng.standard_normal((stop - start, obs_dim), dtype=np.float32)
            dsets["next_observations"][start:stop] = rng.standard_normal(
                (stop - start, obs_dim), dtype=np.float32
            )
            dsets["actions"][start:stop] = rng.uniform(-1, 1, (stop - start, act_dim)).astype(np.float32)
            dsets["rewards"][start:stop] = rng.uniform(0, 2, stop - start).astype(np.float32)
            dsets["costs"][start:stop] = (rng.uniform(size=stop - start) < 0.04).astype(np.float32)
            dsets["terminals"][start:stop] = 0.0
            dsets["timeouts"][start:stop] = ((rows + 1) % episode_length == 0).astype(np.float32)


def measure(path: Path, memmap_dir: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), memmap_dir], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--transitions", type=int, default=3_000_000)
    parser.add_argument("--obs-dim", type=int, default=34)
    parser.add_argument("--act-dim", type=int, default=8)
    parser.add_argument("--episode-length", type=int, default=1000)
    parser.add_argument("--compression", choices=["none", "gzip"], default="none")
    args = parser.parse_args()
    compression = None if args.compression == "none" else "gzip"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.hdf5"
        start = time.perf_counter()
        write_dataset(path, args.transitions, args.obs_dim, args.act_dim, args.episode_length, compression)
        print(
            f"wrote {args.transitions:,} transitions (obs {args.obs_dim}, act {args.act_dim}, "
            f"compression {args.compression}) in {time.perf_counter() - start:.1f} s, "
            f"file {path.stat().st_size / 2**20:.0f} MiB"
        )
        for label, memmap_dir in (("in memory", ""), ("memory-mapped", str(Path(tmp) / "mm"))):
            r = measure(path, memmap_dir)
            print(
                f"  {label:14s}: load {r['load_s']:6.2f} s, label {r['label_s']:5.2f} s, "
                f"peak extra RSS {r['extra_mib']:6.0f} MiB for {r['held_mib']:5.0f} MiB of arrays "
                f"(ratio {r['extra_mib'] / r['held_mib']:.2f}), anonymous memory kept {r['anon_mib']:5.0f} MiB; "
                f"{r['episodes']} episodes, "
                f"{r['safe']} safe, {r['performant']} performant"
            )


if __name__ == "__main__":
    main()
