"""The ledger's history and committed snapshot (src/report/ledger_history.py): every write appends its
statuses, a change between two writes is listed, and the snapshot is written by the ledger stage from a
store, named by the store's fingerprint and free of machine paths."""

import pandas as pd
from omegaconf import OmegaConf

from src.report.ledger import build_ledger
from src.report.ledger_history import append_history, changes, store_fingerprint
from tests.test_ledger import LEDGER_CLAIMS, ledger_store  # noqa: F401  (the fixture)


def test_the_store_fingerprint_names_the_set_of_runs():
    assert store_fingerprint(["b", "a", "a"]) == store_fingerprint(["a", "b"])
    assert store_fingerprint(["a", "b"]) != store_fingerprint(["a", "c"])
    assert store_fingerprint([]) == "none" and len(store_fingerprint(["a"])) == 16


def test_changes_compare_the_last_two_writes(tmp_path):
    path = tmp_path / "history.csv"
    first = pd.DataFrame({"written": "w1", "claim": ["x", "y"], "status": ["not run", "reproduced"]})
    assert changes(append_history(path, first)).empty  # one write: nothing to compare
    second = pd.DataFrame(
        {"written": "w2", "claim": ["x", "y", "z"], "status": ["underpowered", "reproduced", "not run"]}
    )
    changed = changes(append_history(path, second))
    assert changed.to_dict("records") == [
        {"claim": "x", "before": "not run", "after": "underpowered", "written": "w2"},
        {"claim": "z", "before": "-", "after": "not run", "written": "w2"},
    ]
    assert len(pd.read_csv(path)) == 5  # appended, not replaced


def _cfg(store, tmp_path, snapshot=None, claims=LEDGER_CLAIMS):
    conf = tmp_path / "conf"
    (conf / "profile").mkdir(parents=True, exist_ok=True)
    for profile in ("smoke", "cpu", "paper", "thesis"):
        (conf / "profile" / f"{profile}.yaml").write_text("{}\n")
    (conf / "claims.yaml").write_text(claims)
    ledger = {"claims": str(conf / "claims.yaml"), "out_dir": str(tmp_path / "reports"), "alpha": 0.05}
    return OmegaConf.create(
        {
            "ledger": {**ledger, "snapshot": None if snapshot is None else str(snapshot)},
            "tracking": {"uri": store["uri"]},
            "report": {"site": False},
        }
    )


def test_each_write_appends_and_the_snapshot_is_written_from_the_store(ledger_store, tmp_path):  # noqa: F811
    snapshot = tmp_path / "docs" / "results"
    first = build_ledger(_cfg(ledger_store, tmp_path, snapshot))
    # A second write in which one claim's published size changes its status.
    second = build_ledger(
        _cfg(ledger_store, tmp_path, snapshot, LEDGER_CLAIMS.replace("size: 3}", "size: 0.9}"))
    )
    assert first["statuses"]["kpcn_beats_dpcn_by_3db"] == "direction only"
    assert second["statuses"]["kpcn_beats_dpcn_by_3db"] == "reproduced"
    claims = len(first["statuses"])  # one history line per claim and write
    history = pd.read_csv(tmp_path / "reports" / "ledger_history.csv", dtype=str)
    assert history["written"].nunique() in (1, 2) and len(history) == 2 * claims
    committed = pd.read_csv(snapshot / "history.csv", dtype=str)
    assert len(committed) == 2 * claims
    text = (snapshot / "ledger.csv").read_text()
    header = text.splitlines()[0]
    assert (
        header.startswith("# ledger written ") and "store fingerprint " in header and "counted runs" in header
    )
    assert str(tmp_path) not in text and "sqlite" not in text  # no machine path
    rows = pd.read_csv(snapshot / "ledger.csv", skiprows=1).set_index("claim")
    assert rows.loc["kpcn_beats_dpcn_by_3db", "status"] == "reproduced"  # the latest write
    assert (snapshot / "items" / "kpcn_beats_dpcn.csv").is_file()
    assert (snapshot / "ledger.md").read_text().startswith("# Reproduction ledger")
    # the paths the stage reports: the snapshot's ledger, and the history beside the page
    assert second["paths"]["snapshot"] == snapshot / "ledger.csv"
    assert second["paths"]["history"] == tmp_path / "reports" / "ledger_history.csv"
