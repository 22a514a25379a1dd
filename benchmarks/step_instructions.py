"""Machine instructions per lockstep step of the 45-buoy `aggregation` scenario, physics and kinematic fidelity.

Why instructions: on a shared or virtual host the wall and CPU time of the same
code drift by a factor of two within an hour (a kinematic step took 1.06 ms and
2.0 ms on one machine in one afternoon), so a 10 % change cannot be seen in
them. Valgrind's callgrind counts the instructions executed, which do not
depend on the load; it is about 50 times slower than a normal run, so only
`--steps` steps are counted, after `--warmup` steps run without counting.

    python benchmarks/step_instructions.py [--steps 40] [--warmup 30]

Needs `valgrind` (Debian: apt install valgrind). Prints one JSON line: instructions per step of each fidelity
and their ratio (what the physics step costs in kinematic steps).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile


def count(fidelity: str, steps: int, warmup: int) -> int:
    """Instructions executed by `steps` steps of the fleet at `fidelity` (this script run under callgrind)."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            "valgrind", "--tool=callgrind", "--instr-atstart=no", f"--callgrind-out-file={tmp}/out",
            sys.executable, __file__, "--inside", fidelity, "--steps", str(steps), "--warmup", str(warmup),
        ]  # fmt: skip
        result = subprocess.run(command, capture_output=True, text=True, check=False)
        found = re.search(r"Collected : (\d+)", result.stderr)
        if result.returncode != 0 or found is None:
            raise SystemExit(f"callgrind run failed ({result.returncode}):\n{result.stderr[-2000:]}")
        return int(found.group(1))


def inside(fidelity: str, steps: int, warmup: int) -> None:
    """The counted part: build the fleet and warm it up uncounted, then count `steps` steps."""
    from sitl.experiments.scenario import load_scenario
    from sitl.fleets.fleet import LockstepFleet

    fleet = LockstepFleet(load_scenario("aggregation").with_overrides(fidelity=fidelity))
    for _ in range(warmup):
        fleet.step()
    subprocess.run(["callgrind_control", "--instr=on", str(os.getpid())], capture_output=True, check=False)
    for _ in range(steps):
        fleet.step()
    subprocess.run(["callgrind_control", "--instr=off", str(os.getpid())], capture_output=True, check=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40, help="steps counted (0.5 s each)")
    parser.add_argument("--warmup", type=int, default=30, help="steps run first, not counted")
    parser.add_argument("--inside", choices=["physics", "kinematic"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.inside:
        inside(args.inside, args.steps, args.warmup)
        return
    if shutil.which("valgrind") is None or shutil.which("callgrind_control") is None:
        raise SystemExit("step_instructions needs valgrind (apt install valgrind)")
    physics = count("physics", args.steps, args.warmup) / args.steps
    kinematic = count("kinematic", args.steps, args.warmup) / args.steps
    print(
        json.dumps(
            {
                "scenario": "aggregation",
                "agents": 45,
                "steps": args.steps,
                "physics_instructions_per_step": round(physics),
                "kinematic_instructions_per_step": round(kinematic),
                "physics_cost_ratio": round(physics / kinematic, 2),
            }
        )
    )


if __name__ == "__main__":
    main()
