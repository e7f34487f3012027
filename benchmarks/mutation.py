"""Mutation scores of the safety-critical code: the shield (with its dead reckoning), the
action grammar, the reply parser (`make mutate`; outside CI, some tens of minutes on 2 cores).

mutmut (configured under ``[tool.mutmut]`` in pyproject.toml) changes one operator,
number or name at a time in those modules and runs the quick tests that cover the
function it changed; a mutant the tests do not notice "survived". It works on a copy of
the tree in ``.mutation/`` (mutmut writes its mutants beside the sources it is given),
and prints, per module, how many were killed, the score, and the names of the survivors,
to read with ``cd .mutation && mutmut show NAME``. Targets (issue 29): at least 85% for
the shield, 90% for actions.
"""

from __future__ import annotations

import collections
import re
import shutil
import subprocess
import sys
from pathlib import Path

MUTMUT = Path(sys.executable).with_name("mutmut")
ROOT = Path(__file__).resolve().parents[1]
COPY = ROOT / ".mutation"
KNOWN = ("killed", "timeout", "survived")
# The shield's dead reckoning and back-projection live in cavenav.safety.reckoning: counted with it.
TARGETS = {
    "cavenav.safety.shield": 85.0,
    "cavenav.safety.reckoning": 85.0,
    "cavenav.motion.actions": 90.0,
    "cavenav.pilots.reply": None,
}


def main() -> None:
    shutil.rmtree(COPY, ignore_errors=True)
    for part in ("src", "tests", "examples"):
        shutil.copytree(ROOT / part, COPY / part, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", COPY)
    mutmut = {"cwd": COPY, "check": True}
    subprocess.run([MUTMUT, "run", "--max-children", "2"], stdout=subprocess.DEVNULL, **mutmut)
    listing = subprocess.run(
        [MUTMUT, "results", "--all", "true"], capture_output=True, text=True, **mutmut
    ).stdout
    statuses: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    survivors: dict[str, list[str]] = collections.defaultdict(list)
    for name, module, status in re.findall(r"^\s*((\S+?)\.x\S*): (\S+)$", listing, re.M):
        statuses[module][status] += 1
        if status == "survived":
            survivors[module].append(name)
    for module, target in TARGETS.items():
        counts = statuses[module]
        killed = counts["killed"] + counts["timeout"]
        # "suspicious": the tests ran far slower than unmutated (a loaded machine, or a
        # mutant that loops); neither killed nor survived, so left out of the score.
        judged = killed + counts["survived"]
        score = 100.0 * killed / judged if judged else 0.0
        goal = f" (target {target:.0f}%)" if target else ""
        others = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()) if s not in KNOWN)
        print(
            f"{module}: {killed} killed, {counts['survived']} survived: {score:.1f}%{goal}"
            + (f"; not judged: {others}" if others else "")
        )
        for name in survivors[module]:
            print(f"  survived: {name}")


if __name__ == "__main__":
    main()
