"""The ledger's memory: every write appends one line per claim to a history (date, commit, the store it
read, the claim, its status and the numbers behind it), so a status that changes is visible and the
site can say what changed (`changes`). A committed snapshot (`write_snapshot`) is the ledger as a command
wrote it from a store, named by the store's fingerprint (the runs it read), never a hand-edited copy; it
holds no machine path.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from src.io.atomic import atomic_write_text

HISTORY_COLUMNS = (
    "written",
    "commit",
    "store",
    "claim",
    "category",
    "profile",
    "status",
    "replicates",
    "unit",
    "seeds",
    "images",
    "measured",
    "p",
    "p_adjusted",
)
SNAPSHOT_FILES = ("ledger.csv", "ledger.md", "history.csv")


def store_fingerprint(run_ids: Iterable[str]) -> str:
    """16 hex digits naming the set of runs the ledger read: the same store (and selection) gives the same
    fingerprint on any machine; "none" when it read no run."""
    ids = sorted(set(run_ids))
    if not ids:
        return "none"
    return hashlib.sha256("\n".join(ids).encode()).hexdigest()[:16]


def history_lines(frame: pd.DataFrame, written: str, commit: str, store: str) -> pd.DataFrame:
    """This write's lines: one per claim of the ledger `frame` (`ledger_page.ledger_frame`)."""
    lines = frame.assign(written=written, commit=commit, store=store)
    return lines[list(HISTORY_COLUMNS)]


def append_history(path: Path, lines: pd.DataFrame) -> pd.DataFrame:
    """`path` with `lines` appended (created when missing), written atomically; returns the whole history.
    A history with other columns (an older version) is kept: the new lines fill the columns they have."""
    path = Path(path)
    if path.is_file() and path.stat().st_size:
        history = pd.concat([pd.read_csv(path, dtype=str), lines.astype(str)], ignore_index=True)
    else:
        history = lines.astype(str)
    atomic_write_text(path, history.to_csv(index=False))
    return history


def changes(history: pd.DataFrame) -> pd.DataFrame:
    """The claims whose status differs between the last two writes of `history` (columns claim, before,
    after, written); a claim new in the last write reads before = "-". Empty with fewer than two writes."""
    writes = list(dict.fromkeys(history["written"]))  # in the order written
    if len(writes) < 2:
        return pd.DataFrame(columns=["claim", "before", "after", "written"])
    before = history[history["written"] == writes[-2]].set_index("claim")["status"]
    after = history[history["written"] == writes[-1]].set_index("claim")["status"]
    rows = [
        {"claim": claim, "before": before.get(claim, "-"), "after": status, "written": writes[-1]}
        for claim, status in after.items()
        if before.get(claim, "-") != status
    ]
    return pd.DataFrame(rows, columns=["claim", "before", "after", "written"])


def write_snapshot(
    folder: Path, header: str, csv_text: str, md_text: str, lines: pd.DataFrame, items: Iterable[Path] = ()
) -> list[Path]:
    """The committed snapshot in `folder`: `ledger.csv` (`# <header>` then the ledger's CSV), `ledger.md`,
    `items/` holding this write's per-replicate CSVs (`items`) and no older ones, and `history.csv` with
    this write's lines appended."""
    import shutil

    folder = Path(folder)
    written = [
        atomic_write_text(folder / "ledger.csv", f"# {header}\n{csv_text}"),
        atomic_write_text(folder / "ledger.md", md_text),
    ]
    shutil.rmtree(folder / "items", ignore_errors=True)
    for item in items:
        (folder / "items").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(item, folder / "items" / Path(item).name)
    append_history(folder / "history.csv", lines)
    return [*written, folder / "history.csv"]
