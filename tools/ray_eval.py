"""`vkdr eval` or `vkdr eval-frames` across a Ray cluster: one Ray task per shard, merged
when all are done.

    pip install "ray[default]"
    python3 tools/ray_eval.py --address auto --shards 8 --gpus-per-task 1 --out OUT -- \\
        --dataset DATA --trials 10 --depth
    python3 tools/ray_eval.py --command eval-frames --address auto --shards 8 --out OUT -- \\
        FRAMES --categories MAP.json --trials 3

Each task runs `vkdr COMMAND <args> --shard K/N` on a worker into a temporary folder and
returns the shard's rows (`shard.json`); the driver writes them under OUT/shards/K and runs
`vkdr COMMAND --merge OUT OUT/shards/*`, so the tables in OUT are the bytes one process
would write (the wall times aside). Every worker needs the `vkdr` binary (`--vkdr`, by default
this checkout's target/release/vkdr) and the dataset or frames at the paths given; pass
`--spaces DIR` among the eval arguments, on a shared file system, to build each category's
shape space once. A task that fails is retried up to `--retries` times (2), then reported;
the merge then names the missing shard. `--address local` starts a local Ray with
`--num-cpus` CPUs (2) instead of joining a cluster.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import ray

ROOT = Path(__file__).resolve().parents[1]


def parse():
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        usage="%(prog)s [options] --out OUT -- EVAL_ARGS...",
    )
    parser.add_argument("--command", choices=["eval", "eval-frames"], default="eval",
                        help="the vkdr command the shards run (eval: a generated dataset; eval-frames: BOP frames)")
    parser.add_argument("--address", default="auto", help="Ray cluster address; 'local' starts one here")
    parser.add_argument("--num-cpus", type=int, default=2, help="CPUs of a local Ray (--address local)")
    parser.add_argument("--shards", type=int, required=True, help="shards (Ray tasks), N")
    parser.add_argument("--gpus-per-task", type=float, default=1.0, help="GPUs each task reserves (0: none)")
    parser.add_argument("--cpus-per-task", type=float, default=1.0, help="CPUs each task reserves")
    parser.add_argument("--retries", type=int, default=2, help="retries of a failed task")
    parser.add_argument("--vkdr", default=str(ROOT / "target" / "release" / "vkdr"), help="the vkdr binary on the workers")
    parser.add_argument("--out", required=True, type=Path, help="the merged tables' folder (new or empty)")
    parser.add_argument("eval_args", nargs=argparse.REMAINDER, help="-- then the command's arguments")
    args = parser.parse_args()
    eval_args = args.eval_args[1:] if args.eval_args[:1] == ["--"] else args.eval_args
    for flag in ("--out", "--shard", "--merge"):
        if any(a == flag or a.startswith(flag + "=") for a in eval_args):
            parser.error(f"{flag} among the {args.command} arguments: ray_eval.py sets it")
    needs = "--dataset" if args.command == "eval" else "--categories"
    if not any(a == needs or a.startswith(needs + "=") for a in eval_args):
        parser.error(f"the {args.command} arguments need {needs}")
    if args.shards < 1:
        parser.error("--shards must be at least 1")
    if args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out {args.out} already holds files: give an empty or new folder")
    args.eval_args = eval_args
    return args


@ray.remote
def run_shard(binary, command, eval_args, index, count):
    """Runs shard index/count; returns (index, shard.json's text, seconds, the host)."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="vkdr_shard_") as tmp:
        out = Path(tmp) / "out"
        done = subprocess.run(
            [binary, command, *eval_args, "--shard", f"{index}/{count}", "--out", str(out)],
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            tail = "\n".join(done.stderr.strip().splitlines()[-5:])
            raise RuntimeError(f"shard {index}/{count} on {os.uname().nodename}: vkdr {command} exited {done.returncode}:\n{tail}")
        text = (out / "shard.json").read_text()
    return index, text, time.perf_counter() - start, os.uname().nodename


def main():
    args = parse()
    if args.address == "local":
        ray.init(num_cpus=args.num_cpus)
    else:
        ray.init(address=args.address)
    print(f"ray {ray.__version__}: {args.shards} shards of vkdr {args.command} {' '.join(args.eval_args)}", file=sys.stderr)
    start = time.perf_counter()
    task = run_shard.options(
        num_gpus=args.gpus_per_task,
        num_cpus=args.cpus_per_task,
        max_retries=args.retries,
        retry_exceptions=True,
    )
    pending = {task.remote(args.vkdr, args.command, args.eval_args, k, args.shards): k for k in range(args.shards)}
    shard_dirs, failed = [], []
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        index = pending.pop(ready[0])
        try:
            _, text, seconds, host = ray.get(ready[0])
        except Exception as error:  # noqa: BLE001 - reported, the others go on
            failed.append(index)
            print(f"shard {index}/{args.shards} failed after {args.retries} retries: {error}", file=sys.stderr)
            continue
        folder = args.out / "shards" / str(index)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "shard.json").write_text(text)
        shard_dirs.append(folder)
        done = args.shards - len(pending)
        print(f"[{done}/{args.shards}] shard {index} done on {host} in {seconds:.1f} s "
              f"({time.perf_counter() - start:.1f} s so far)", file=sys.stderr)
    if failed:
        print(f"{len(failed)} shard(s) failed ({', '.join(map(str, sorted(failed)))}): no merge", file=sys.stderr)
        return 1
    merge = subprocess.run(
        [args.vkdr, "--force", args.command, "--merge", str(args.out), *map(str, sorted(shard_dirs))],
        text=True,
    )
    print(f"ray_eval: {args.shards} shards in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return merge.returncode


if __name__ == "__main__":
    sys.exit(main())
