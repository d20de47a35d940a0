"""What every result carries: the resolved config, the git commit and a fingerprint of the data."""

from __future__ import annotations

import hashlib
import json
import logging
import subprocess
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.io.atomic import atomic_write_json

log = logging.getLogger("nrbench")


def git_commit(repo: Path | None = None) -> str:
    """HEAD's commit hash, with ``+dirty`` when tracked files differ from it; ``unknown`` outside git."""
    cwd = repo or Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, check=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=cwd,
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


#: The folder inside a data folder (or any folder of one) where the render stage sets aside the renders of
#: another configuration (`src.render.stale_renders`): not part of the data the folder holds.
PARKED_DIR = ".parked"


def data_fingerprint(directory: Path) -> str:
    """Hash of every file's relative path and size, plus the render manifest's content if present
    (``manifest.json``, or the per-file entries under ``manifest/`` of the volumetric data).

    Cheap on paper-scale data (hundreds of GB): contents are not read, except the manifest, whose
    render keys already hash what produced each file. Files being written by another job (the hidden
    temporaries of ``src.io.atomic``, or one renamed away meanwhile) are left out, and so are the renders
    set aside for another configuration (`PARKED_DIR`): which other configs rendered here must not change
    this one's data (nor the prepared folder's cache key made from it).
    """
    h = hashlib.sha256()
    for path in sorted(p for p in directory.rglob("*") if p.is_file()):
        if path.name.startswith(".") and ".tmp-" in path.name:
            continue
        if PARKED_DIR in path.relative_to(directory).parts:
            continue
        try:
            size = path.stat().st_size
            content = path.read_bytes() if _is_manifest(path, directory) else b""
        except FileNotFoundError:
            continue
        h.update(f"{path.relative_to(directory)}:{size}\n".encode())
        h.update(content)
    return h.hexdigest()[:16]


def _is_manifest(path: Path, directory: Path) -> bool:
    return path.name == "manifest.json" or path.parent == directory / "manifest"


#: Config keys that say where things go, not what is computed: they never make two runs incomparable.
#: The seed is listed too because reports aggregate over it.
IGNORED_PARAM_PREFIXES = ("paths.", "hydra", "tracking.", "report.", "ledger.", "export.", "compare.")
IGNORED_PARAMS = frozenset(
    {
        "task.train.checkpoint_dir",
        "task.train.curves_file",
        "task.eval.out_dir",
        "task.eval.checkpoint",
        "task.train.resume",
        "task.search.out_dir",  # task=filter_search: per job
        "task.search.resume",
        "dataset.feature_selection.dir",  # under paths.dataset; what it holds is the selection's data
        "task.search.seed",  # = ${seed}, which reports aggregate over
        "stage",
        "seed",
        "auto_resume",  # whether a job continues its checkpoint; the result is the same either way
        "skip_finished",  # whether a job already done runs again; the same
    }
)


def ignored_param(key: str) -> bool:
    """Whether dotted config key `key` is a path, output location or otherwise irrelevant to results."""
    return key in IGNORED_PARAMS or key.startswith(IGNORED_PARAM_PREFIXES)


def result_config(cfg: DictConfig) -> dict:
    """The resolved config minus what `ignored_param` names (the seed stays): everything that decides a
    result and nothing machine- or run-specific, so it is equal on every clone (DVC params/deps)."""

    def keep(prefix: str, node):
        if not isinstance(node, dict):
            return node
        out = {}
        for key, value in node.items():
            dotted = f"{prefix}{key}"
            if dotted != "seed" and (ignored_param(dotted) or ignored_param(f"{dotted}.")):
                continue
            out[key] = keep(f"{dotted}.", value)
        return out

    return keep("", OmegaConf.to_container(cfg, resolve=True))


def config_digest(cfg: DictConfig) -> str:
    """A short hash of `result_config(cfg)` (seed included): two configs with the same digest compute the
    same result. A checkpoint carries the digest of the config that wrote it, so that a job starting again
    in the same folder continues it only when nothing that decides the result has changed."""
    text = json.dumps(result_config(cfg), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def continued_in_place(cfg: DictConfig, path: Path, digest_of: Callable[[Path], str | None]) -> bool:
    """Whether a job of `cfg` continues the checkpoint at `path` by itself (`auto_resume`): it is there and
    the same configuration wrote it (`digest_of(path)`: the digest it records, None for a version that
    recorded none); says why not in one warning."""
    if not cfg.get("auto_resume", False) or not path.is_file():
        return False
    written = digest_of(path)
    if written == config_digest(cfg):
        return True
    log.warning(
        "%s: not continued: written by %s; starting over (task.train.resume=<path> continues it anyway)",
        path,
        "another configuration" if written else "a version that recorded no configuration digest",
    )
    return False


def provenance(cfg: DictConfig, data_dir: Path | None = None) -> dict:
    record = {"git_commit": git_commit(), "config": OmegaConf.to_container(cfg, resolve=True)}
    if data_dir is not None and data_dir.exists():
        record["data_fingerprint"] = data_fingerprint(data_dir)
    return record


def write_summary(path: Path, summary: dict, cfg: DictConfig, data_dir: Path, **extra) -> None:
    """A stage's JSON summary, atomically, with the provenance of its result (config, commit, data)."""
    atomic_write_json(path, {"summary": summary, **extra, **provenance(cfg, data_dir)})
