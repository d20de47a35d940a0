"""Which configurations already have a FINISHED run in the tracking store, and how long those runs took.

Every job's run carries the digest of its result-deciding config (`nrbench.config_digest`, see
`src.provenance.config_digest`): a job with `skip_finished=true` whose digest has a FINISHED run ends at
once, and `python -m src.studies` counts a study's jobs as done by it and estimates the rest from the
durations of the done ones.
"""

from __future__ import annotations

from dataclasses import dataclass

from mlflow.tracking import MlflowClient

DIGEST_TAG = "nrbench.config_digest"


@dataclass(frozen=True)
class FinishedRun:
    run_id: str
    seconds: float  # wall clock from the run's start to its end (across a requeue: the whole span)
    model: str


def finished_runs(uri: str, experiment: str, digest: str | None = None) -> dict[str, FinishedRun]:
    """{config digest: its newest FINISHED run} of experiment `experiment` in the store at `uri` ({} when
    the experiment does not exist yet); with `digest`, that digest's only (one query, however large the
    store). Runs logged before runs carried the digest are not among them."""
    client = MlflowClient(tracking_uri=uri)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        return {}
    tagged = f"tags.`{DIGEST_TAG}` = '{digest}'" if digest else f"tags.`{DIGEST_TAG}` != ''"
    runs = client.search_runs(
        [found.experiment_id],
        filter_string=f"attributes.status = 'FINISHED' and {tagged}",
        order_by=["attributes.start_time ASC"],
        max_results=50_000,
    )
    return {
        run.data.tags[DIGEST_TAG]: FinishedRun(
            run.info.run_id,
            (run.info.end_time - run.info.start_time) / 1000.0,
            run.data.params.get("model.name", ""),
        )
        for run in runs
        if run.info.end_time
    }
