#!/usr/bin/env bash
# Mutation testing of the pure numeric modules (mutmut 3): does the test suite notice a wrong number?
#
#   bash scripts/mutation.sh                  # every group in [tool.nrbench.mutation] (pyproject.toml)
#   bash scripts/mutation.sh kpcn nerf        # only these groups ([tool.nrbench.mutation.*] in pyproject.toml)
#
# Each group's modules are mutated and every mutant is run against that group's own test files only
# (mutmut runs, per mutant, just the tests that call the mutated function). Results: one JSON per group in
# .mutation/ (survivors with their diffs in .mutation/<group>-survivors.txt), then a per-module table of
# killed / total. Work dir: mutants/ (recreated per group). Both are git-ignored. Not part of
# scripts/test.sh or the default pytest run. MUTATION_JOBS (default 1) sets mutmut's parallel workers.
# MUTATION_MUTANTS (space-separated mutmut names, globs allowed, e.g.
# 'src.report.ledger.x_build_ledger__mutmut_*') runs only those mutants of one group; the others count as
# "not checked". A group too long for one sitting can so be split over worktrees running side by side.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh

# Tiny tensors: one thread per worker avoids oversubscription and OpenMP's fork hazards.
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
export MUTATION_JOBS="${MUTATION_JOBS:-1}"
mkdir -p .mutation

groups=("$@")
if [ ${#groups[@]} -eq 0 ]; then
  mapfile -t groups < <(.venv/bin/python -c \
    'import tomllib; print("\n".join(tomllib.load(open("pyproject.toml", "rb"))["tool"]["nrbench"]["mutation"]))')
fi

for group in "${groups[@]}"; do
  echo "== mutation: $group"
  rm -rf mutants
  start=$(date +%s)
  # mutmut's own stdout (progress spinner) goes to the log; the summary is printed below.
  .venv/bin/python - "$group" >".mutation/$group.log" 2>&1 <<'PY' || { tail -40 ".mutation/$group.log"; exit 1; }
"""Run mutmut 3 on one group, with two patches for this repository's layout, then save the results."""

import ast
import json
import os
import sys
import tomllib
from pathlib import Path

import mutmut.__main__ as mm
import mutmut.mutation.trampoline as trampoline
import mutmut.utils.format_utils as format_utils
from mutmut.configuration import config
from mutmut.mutation.data import SourceFileMutationData
from mutmut.mutation.diff_apply import get_diff_for_mutant
from mutmut.state import state
from mutmut.stats import status_by_exit_code

group = sys.argv[1]
groups = tomllib.loads(Path("pyproject.toml").read_text())["tool"]["nrbench"]["mutation"]
if group not in groups:
    sys.exit(f"unknown mutation group {group!r}; expected one of {', '.join(groups)}")
spec = groups[group]

# 1. mutmut drops a leading "src." from module names (it expects src/ to be a layout folder on sys.path);
#    here `src` is the package (`import src.data.kpcn_preprocess`), so keep the prefix. Then the mutant
#    keys match the trampolines' `__module__` and the tests' import path.
_strip_prefix = format_utils.strip_prefix


def strip_prefix(s, *, prefix, strict=False):
    return s if prefix == "src." else _strip_prefix(s, prefix=prefix, strict=strict)


format_utils.strip_prefix = strip_prefix


# 2. ...and asserts that no recorded name starts with "src."; the same bookkeeping without that assert
#    (max_stack_depth is left at -1, so the frame walk of the original is not needed).
def record_trampoline_hit(name, caller=None):
    state()._stats.add(name)
    if caller is not None and config().track_dependencies:
        state().function_dependencies[name].add(caller)


trampoline.record_trampoline_hit = record_trampoline_hit


# 3. Put only mutants/ on sys.path (mutmut also adds mutants/src, whose src/io, src/eval... would shadow
#    top-level modules of that name), and never the original sources.
def setup_source_paths():
    here = Path(".").resolve()
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != here]
    sys.path.insert(0, str(Path("mutants").absolute()))


mm.setup_source_paths = setup_source_paths

cfg = config()
assert cfg.max_stack_depth == -1
cfg.only_mutate = list(spec["mutate"])
cfg.pytest_add_cli_args_test_selection = list(spec["tests"])
# A test that runs `python -m src.run` in a subprocess cannot run under mutmut: the child inherits its
# MUTANT_UNDER_TEST but not the patches above, so its trampolines fail. A group lists those in `deselect`
# (the CLI path is covered by the suite itself).
for test in spec.get("deselect", []):
    cfg.pytest_add_cli_args_test_selection += ["--deselect", test]
module_globs = [p[: -len(".py")].replace("/", ".") + ".*" for p in spec["mutate"]]
chosen = os.environ.get("MUTATION_MUTANTS", "").split()
mm._run(chosen or module_globs, int(os.environ.get("MUTATION_JOBS", "1")))


def source_line(path, diff):
    """Line in the original file of the first line the mutant changed."""
    removed = next((ln[1:].strip() for ln in diff.splitlines()[2:] if ln.startswith("-")), None)
    lines = Path(path).read_text().splitlines()
    func = diff.splitlines()[2:]
    if removed is None:
        return 0
    # search within the function, found from its `def` line in the diff
    defs = [ln[1:].strip() for ln in func if ln.startswith(" def ") or ln.startswith(" async def ")]
    start = 0
    for node in ast.walk(ast.parse(Path(path).read_text())):
        if isinstance(node, ast.FunctionDef) and defs and defs[0].startswith(f"def {node.name}("):
            start = node.lineno - 1
            break
    for i in range(start, len(lines)):
        if lines[i].strip() == removed:
            return i + 1
    return 0


results = {}
for path in spec["mutate"]:
    data = SourceFileMutationData(path=Path(path))
    data.load()
    counts, survivors = {}, []
    for key, code in sorted(data.exit_code_by_key.items()):
        status = status_by_exit_code[code]
        counts[status] = counts.get(status, 0) + 1
        if status not in ("killed", "timeout", "caught by type check"):
            diff = get_diff_for_mutant(key, path=path)
            survivors.append({"mutant": key, "status": status, "line": source_line(path, diff), "diff": diff})
    results[path] = {"counts": counts, "survivors": survivors}
Path(f".mutation/{group}.json").write_text(json.dumps(results, indent=1))
with open(f".mutation/{group}-survivors.txt", "w") as f:
    for path, r in results.items():
        for s in r["survivors"]:
            f.write(f"# {s['mutant']} ({path}:{s['line']}, {s['status']})\n{s['diff']}\n\n")
PY
  echo "   $(($(date +%s) - start)) s (log: .mutation/$group.log)"
done

# Per-module table of every group that has results in .mutation/.
.venv/bin/python - "${groups[@]}" <<'PY'
import json
import sys
from pathlib import Path

print(f"\n{'module':<36} {'killed':>6} {'timeout':>7} {'surv.':>5} {'other':>5} {'total':>5} {'score':>6}")
survivors = []
for group in sys.argv[1:]:
    for path, r in json.loads(Path(f".mutation/{group}.json").read_text()).items():
        c = r["counts"]
        total = sum(c.values())
        killed, timeout, survived = c.get("killed", 0), c.get("timeout", 0), c.get("survived", 0)
        other = total - killed - timeout - survived
        score = 100.0 * (killed + timeout) / total if total else 100.0
        print(f"{path:<36} {killed:>6} {timeout:>7} {survived:>5} {other:>5} {total:>5} {score:>5.1f}%")
        survivors += [f"  {path}:{s['line']}  {s['mutant'].rsplit('.', 1)[1]}  ({s['status']})" for s in r["survivors"]]
print("score = (killed + timeout) / total; 'other' = no tests / suspicious / segfault")
if survivors:
    print(f"\n{len(survivors)} mutants not killed (diffs in .mutation/<group>-survivors.txt):")
    print("\n".join(survivors))
PY
