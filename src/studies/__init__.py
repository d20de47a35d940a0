"""The ledger's studies as jobs: which a study (or the whole ledger) would run at a profile, which are
done in the tracking store, the time left, and one command that launches the rest (`python -m
src.studies`)."""
