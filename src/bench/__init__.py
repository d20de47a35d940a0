"""Benchmarks of the methods' speed, run as ``python -m src.bench denoise|nerf`` (see `cli`).

- `cli`: the command line (arguments, their checks, the one-line errors);
- `denoise`, `denoise_timing`, `denoise_table`: full-frame inference time of the learned denoisers and OIDN,
  timed in rounds; `conv_depth`: a model's conv layers on its longest path; `bench_log`: `--log`'s MLflow run;
- `peak`: the achievable convolution throughput of this device, the denoisers' reference;
- `nerf`, `nerf_timing`, `nerf_table`: training and rendering rays/s of the NeRF-family models;
- `timing`, `model_configs`, `table`: what the benchmarks share (timing, rounds, configs, table lines).
"""
