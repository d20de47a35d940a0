"""Which ledger the site shows, and the line that says where it comes from.

A store's own ledger (`<reports>/ledger.csv`, written by `stage=ledger`) is shown once it has a status: at
least one claim that ran. Until then (a fresh clone after the Quickstart: every claim "not run") the site
shows the committed snapshot (`report.committed_ledger`, docs/results/ledger.csv), labelled with the
commit, date and store it was written from and the profiles and machines of its runs, so that a new
reader sees the findings instead of an empty table. No machine path is printed: a file is named relative
to the repository, or by its name.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from src.report.collect import display_path
from src.report.verdicts import NOT_RUN

LOCAL, COMMITTED, NONE = "local", "committed", "none"


@dataclass(frozen=True)
class ShownLedger:
    """The ledger's rows (`ledger_page.COLUMNS`, as strings), where they come from (`LOCAL`, `COMMITTED`
    or `NONE`: no ledger at all), a one-line label, and the methods sentence of the page it was written
    with ("" when unknown)."""

    frame: pd.DataFrame
    origin: str
    label: str
    subtitle: str = ""
    folder: Path | None = None  # where its CSV lies: its items/ are beside it

    def items_href(self, page_dir: Path):
        """The link, from a page in `page_dir`, to a claim's per-replicate CSV (the `items_csv` column,
        relative to the ledger's folder), or None when the file is not there."""

        def href(link: str) -> str | None:
            if self.folder is None or not (self.folder / link).is_file():
                return None
            return Path(os.path.relpath(self.folder / link, page_dir)).as_posix()

        return href


def read_ledger(path: Path) -> tuple[pd.DataFrame, str]:
    """A ledger CSV as strings (missing cells "-") and its `# ...` header line ("" without one)."""
    path = Path(path)
    with path.open(encoding="utf-8") as f:
        first = f.readline()
    header = first[1:].strip() if first.startswith("#") else ""
    frame = pd.read_csv(path, dtype=str, skiprows=1 if header else 0).fillna("-")
    return frame, header


def has_status(frame: pd.DataFrame) -> bool:
    """Whether any claim ran (a status other than "not run")."""
    return bool(len(frame)) and bool((frame["status"] != NOT_RUN).any())


def runs_summary(frame: pd.DataFrame) -> str:
    """ "profiles cpu (49 claims); measured on <device card>, ..." over the claims that ran: the devices
    from each row's `measured_on` (its cards before the cost figures, run counts left out)."""
    ran = frame[frame["status"] != NOT_RUN]
    profiles = ran["profile"].value_counts()
    text = "profiles " + ", ".join(f"{p} ({n} claims)" for p, n in profiles.items())
    cards: dict[str, None] = {}
    for value in ran.get("measured_on", pd.Series(dtype=str)):
        for card in str(value).split(";"):
            card = card.strip()
            if card.endswith(" runs)") or card.endswith(" run)"):
                cards[card.rsplit(" (", 1)[0]] = None
    return text + (f"; measured on {', '.join(cards)}" if cards else "")


def _subtitle(csv_path: Path) -> str:
    """The methods sentence of the ledger.md written beside `csv_path` (its third line), or ""."""
    md = Path(csv_path).with_suffix(".md")
    if not md.is_file():
        return ""
    lines = md.read_text(encoding="utf-8").splitlines()
    return lines[2].strip() if len(lines) > 2 else ""


def _local_label(path: Path) -> str:
    history = path.parent / "ledger_history.csv"
    written = ""
    if history.is_file():
        last = pd.read_csv(history, dtype=str).iloc[-1]
        written = f", written {last.get('written', '?')} at commit {last.get('commit', '?')}"
        written += f" (store {last.get('store', '?')})"
    return f"This store's ledger ({path.name}{written})"


def choose(local: Path, committed: Path | None) -> ShownLedger:
    """The store's own ledger at `local` when it has a status, else the committed snapshot when it exists
    (and has one), else the store's own (all not run), else `NONE` (an empty frame)."""
    local = Path(local)
    own = read_ledger(local)[0] if local.is_file() else None
    if own is not None and has_status(own):
        return ShownLedger(own, LOCAL, _local_label(local), _subtitle(local), local.parent)
    if committed is not None and Path(committed).is_file():
        frame, header = read_ledger(Path(committed))
        if has_status(frame):
            reason = (
                "this store's ledger has no status yet" if own is not None else "this store has no ledger"
            )
            label = (
                f"Committed snapshot {display_path(Path(committed))} ({reason}): {header or 'no header'}; "
                f"{runs_summary(frame)}"
            )
            return ShownLedger(frame, COMMITTED, label, _subtitle(Path(committed)), Path(committed).parent)
    if own is not None:
        label = _local_label(local) + ": no claim has runs yet"
        return ShownLedger(own, LOCAL, label, _subtitle(local), local.parent)
    return ShownLedger(pd.DataFrame(columns=["claim", "status"]), NONE, "No ledger yet")
