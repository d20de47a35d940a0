"""dvc.yaml against what its stages really do: one stage of each kind runs in-process, as its `cmd` says
(smoke profile), in an empty workspace, and every file it reads or writes there must be a declared dep or
out of that stage, and every declared out must exist afterwards. Reads and writes are seen through
Python's audit hooks (`open`, directory listings, renames) plus a before/after snapshot of the workspace
(which also catches files written by C libraries: OpenEXR, Mitsuba). Unlike test_dvc_pipeline.py (slow,
a real `dvc repro`), this one runs in the default suite."""

import os
import re
import shlex
import sys
from pathlib import Path

import yaml
from dvc.repo import Repo

from src.run import _tracked_run
from src.stages import STAGES
from tests.conftest import ROOT, compose_config

# One stage of each kind, in pipeline order (a later one needs the earlier ones' outs).
SAMPLE = [
    "render",
    "preprocess",
    "denoise_config@resnet",
    "denoise_train@resnet",
    "denoise_eval@resnet",
    "denoise_baseline@cross_bilateral",
    "denoise_report",
    "nerf_render",
    "nerf_config@nerf-tabletop",
    "nerf_train@nerf-tabletop",
    "nerf_eval@nerf-tabletop",
    "nerf_report",
    "site",
]
# The MLflow store is deliberately no DVC out: the report stages read runs, which DVC cannot hash.
NOT_DVC_MANAGED = ("mlflow.db", "mlartifacts")
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
# src/io/atomic.py's temporary names, `.<name>.tmp-<pid>-<hex>[<suffix>]`: they count as `<name>`.
_ATOMIC_TMP = re.compile(r"^\.(.+)\.tmp-\d+-[0-9a-f]+(\.\w+)?$")
_seen: list[tuple[str, str]] | None = None  # (read|write, path) while a stage runs
#: The profile params.yaml gives the pipeline; the stages run here at `smoke` instead.
PROFILE = yaml.safe_load((ROOT / "params.yaml").read_text())["profile"]


def _at_smoke(path: str) -> str:
    """A declared path as a stage run at the smoke profile writes it: the data folders are per profile
    (`data/<dataset>/<profile>/...`, conf/config.yaml's paths.dataset)."""
    return re.sub(rf"^data/([^/]+)/{PROFILE}(?=/|$)", r"data/\1/smoke", path)


def _audit(event: str, args: tuple) -> None:
    if _seen is None:
        return
    if event == "open" and isinstance(args[0], str | bytes | os.PathLike):
        mode, flags = args[1], args[2]
        writes = any(c in mode for c in "wax+") if isinstance(mode, str) else bool(flags & _WRITE_FLAGS)
        _seen.append(("write" if writes else "read", os.fsdecode(args[0])))
    elif event in ("os.listdir", "os.scandir") and args and isinstance(args[0], str | bytes | os.PathLike):
        _seen.append(("read", os.fsdecode(args[0])))
    elif event == "os.rename":
        _seen.append(("write", os.fsdecode(args[1])))


sys.addaudithook(_audit)


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(root)): (p.stat().st_mtime_ns, p.stat().st_size)
        for p in root.rglob("*")
        if p.is_file()
    }


def _inside(path: str, declared: list[str]) -> bool:
    return any(path == d or path.startswith(d + "/") for d in declared)


def _stage_config(cmd: str, workspace: Path):
    """The config `cmd` composes, at the smoke profile, with the workspace as the repository root."""
    args = shlex.split(cmd)
    assert args[:3] == ["python", "-m", "src.run"], cmd
    overrides = [
        a.replace(f"profile={PROFILE}", "profile=smoke") for a in args[3:] if not a.startswith("hydra")
    ]
    run_dir = next((a.split("=", 1)[1] for a in args if a.startswith("hydra.run.dir=")), "outputs")
    return compose_config(
        [
            *overrides,
            f"paths.root={workspace}",
            f"paths.run_dir={run_dir}",
            f"tracking.uri=sqlite:///{workspace}/mlflow.db",
            f"tracking.artifact_root={workspace}/mlartifacts",
        ]
    )


def _run_stage(cfg) -> None:
    if cfg.stage == "report":
        STAGES["report"](cfg, None)
        return
    with _tracked_run(cfg, [cfg.stage]) as tracker:
        STAGES[cfg.stage](cfg, tracker)


def _relative(paths, workspace: Path) -> set[str]:
    """Workspace-relative paths (temporary names replaced by what they become), leaving out paths outside
    the workspace and the MLflow store."""
    out = set()
    for p in paths:
        absolute = Path(os.path.abspath(workspace / p))
        if absolute.is_relative_to(workspace) and absolute != workspace:
            parts = [
                m.group(1) if (m := _ATOMIC_TMP.match(part)) else part
                for part in absolute.relative_to(workspace).parts
            ]
            if parts[0] not in NOT_DVC_MANAGED:
                out.add("/".join(parts))
    return out


def _ancestor(path: str, declared: list[str]) -> bool:
    """`path` is a folder holding a declared path (opened to fsync a rename into it, or created)."""
    return any(d.startswith(path + "/") for d in declared)


def test_every_stage_declares_what_it_reads_and_writes(tmp_path, monkeypatch, mitsuba_variant):
    global _seen
    stages = {s.addressing: s for s in Repo(ROOT).index.stages}
    assert set(SAMPLE) <= set(stages), set(SAMPLE) - set(stages)
    monkeypatch.chdir(tmp_path)  # DVC runs every cmd from the repository root; paths.data=data is relative
    problems = []
    for name in SAMPLE:
        stage = stages[name]
        deps = [_at_smoke(str(d.def_path)) for d in stage.deps]
        outs = [_at_smoke(str(o.def_path)) for o in stage.outs]
        for dep in deps:
            if dep.startswith(("conf", "src")):
                problems += [] if (ROOT / dep).exists() else [f"{name}: dep {dep} does not exist"]
        cfg = _stage_config(stage.cmd, tmp_path)
        before = _snapshot(tmp_path)
        _seen = []
        try:
            _run_stage(cfg)
            seen = _seen
        finally:
            _seen = None
        after = _snapshot(tmp_path)
        changed = {p for p in before.keys() | after.keys() if before.get(p) != after.get(p)}
        written = _relative(changed | {p for kind, p in seen if kind == "write"}, tmp_path)
        # A read of a path that does not exist in the workspace (a relative name some library resolves
        # elsewhere) reads nothing here.
        read = {
            p
            for p in _relative({p for kind, p in seen if kind == "read"}, tmp_path)
            if (tmp_path / p).exists()
        }
        if undeclared := sorted(p for p in written if not _inside(p, outs)):
            problems.append(f"{name} writes outside its outs {outs}: {undeclared}")
        if undeclared := sorted(p for p in read if not (_inside(p, deps + outs) or _ancestor(p, outs))):
            problems.append(f"{name} reads outside its deps {deps}: {undeclared}")
        if missing := [o for o in outs if not (tmp_path / o).exists()]:
            problems.append(f"{name} did not write its declared outs {missing}")
    assert not problems, "\n".join(problems)


def test_no_two_stages_write_the_same_file():
    """Every out (metrics and plots included) belongs to one stage and none lies inside another's, so two
    stages (e.g. parallel `dvc repro -j`) never write the same file."""
    owner: dict[str, str] = {}
    for stage in Repo(ROOT).index.stages:
        for out in stage.outs:
            path = str(out.def_path)
            clash = [p for p in owner if p == path or _inside(path, [p]) or _inside(p, [path])]
            assert not clash, f"{stage.addressing} writes {path}, which {owner[clash[0]]} writes ({clash[0]})"
            owner[path] = stage.addressing
    assert len(owner) > 20  # every stage of the study was seen (render ... report)


#: The config groups a stage reads, by its `stage=` (the stages that list conf files one by one; the
#: others depend on all of `conf`): their deps must name every profile-group file that writes one of them.
READS = {"render": {"dataset"}, "preprocess": {"dataset", "task"}, "ledger": set()}


def _loaded_profile_files(overrides: list[str]) -> dict[str, str]:
    """{conf-relative path: group it writes (its `# @package`)} of the profile-group files these overrides
    load (conf/config.yaml's `optional ..._profile` entries whose file exists)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        choices = compose("config", overrides=overrides, return_hydra_config=True).hydra.runtime.choices
    out = {}
    for group, name in choices.items():
        path = ROOT / "conf" / group / f"{name}.yaml"
        if group.endswith("_profile") and path.is_file():
            out[f"conf/{group}/{name}.yaml"] = path.read_text().splitlines()[0].removeprefix("# @package ")
    return out


def test_a_stage_that_lists_its_conf_files_lists_each_profile_file_it_reads():
    """At params.yaml's profile, as DVC resolves the deps: editing conf/dataset_profile/volumetric_cpu.yaml
    must rerun vol_render, conf/dataset_task_profile/volumetric_cpu.yaml vol_preprocess."""
    checked = 0
    for stage in Repo(ROOT).index.stages:
        deps = {str(d.def_path) for d in stage.deps}
        if "conf" in deps or not any(d.startswith("conf/") for d in deps):
            continue
        args = shlex.split(stage.cmd)[3:]
        kind = next(a.split("=", 1)[1] for a in args if a.startswith("stage="))
        overrides = [a for a in args if "=" in a and not a.startswith("hydra")]
        loaded = _loaded_profile_files(overrides)
        needed = {path for path, group in loaded.items() if group in READS[kind]}
        # a folder dep covers its files (conf/dataset_task_profile: a profile without a file has none)
        lacking = {p for p in needed if not any(p == d or p.startswith(f"{d}/") for d in deps)}
        assert not lacking, f"{stage.addressing}: deps lack {sorted(lacking)}"
        checked += 1
    assert checked == 6  # render, preprocess, vol_render, vol_preprocess, nerf_render, ledger


def test_the_stages_that_read_logged_runs_say_why_they_do_nothing_without_tracking(tmp_path, capsys):
    """`tracking.enabled=false`: the report and the ledger write nothing and print one line each saying
    so (with tracking on they read the store: the ledger and report tests)."""
    cfg = compose_config(["profile=smoke", "tracking.enabled=false", f"report.out_dir={tmp_path}"])
    assert STAGES["report"](cfg, None) == {} and STAGES["ledger"](cfg, None) == {}
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        "report: tracking.enabled is false, so there are no logged runs to report on",
        "ledger: tracking.enabled is false, so there are no logged runs to judge the claims by",
    ]
    assert list(tmp_path.iterdir()) == []
