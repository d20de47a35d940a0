"""Benchmarks of the methods' speed, run as ``python -m src.bench denoise|nerf`` (see `cli`).

- `cli`: the command line (arguments, their checks, the one-line errors);
- `denoise`, `denoise_timing`, `denoise_table`: full-frame inference time of the learned denoisers and OIDN;
- `peak`: the achievable convolution throughput of this device, the denoisers' reference;
- `nerf`, `nerf_timing`, `nerf_table`: training and rendering rays/s of the NeRF-family models;
- `timing`, `model_configs`, `table`: what both benchmarks share (timing, configs, table lines).
"""
