"""Data kinds: what a dataset is, chosen by `dataset._target_` (conf/dataset/*.yaml), the way `task._target_`
chooses what each stage means. A kind owns how its data are made (rendered or ingested), prepared, read by
training and evaluation, and which stages and methods it can serve; the tasks ask their kind instead of
branching on `dataset.name`. See `base.py` for the interface and docs/architecture.md for the kinds."""
