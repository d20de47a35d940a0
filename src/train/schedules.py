"""Learning-rate schedules."""

from __future__ import annotations

import math


def log_linear_lr(
    step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0, delay_mult: float = 1.0
) -> float:
    """mip-NeRF / Ref-NeRF learning rate (Barron et al. 2021, sec. 5; multinerf `learning_rate_decay`).

    Log-linear interpolation from `lr_init` at step 0 to `lr_final` at `max_steps`,
    lr(t) = exp((1 - t) log lr_init + t log lr_final) with t = step / max_steps clipped to [0, 1],
    times a warm-up factor that rises from `delay_mult` to 1 along a quarter sine over `delay_steps`:
    delay_mult + (1 - delay_mult) sin(pi/2 clip(step / delay_steps, 0, 1)). NeRF's exponential decay
    lr_init 0.1^(step / 500k) (its Blender configs' `lrate_decay = 500`, in thousands of steps; 250 is only
    nerf-pytorch's command-line default) is the same curve with lr_final = lr_init * 0.1^(max_steps / 500k):
    5e-5 after the 500k steps of conf/model_task_profile/nerf_paper.yaml, 5e-6 after the 1M of
    nerf_thesis.yaml.
    """
    if delay_steps > 0:
        ramp = min(max(step / delay_steps, 0.0), 1.0)
        warm = delay_mult + (1 - delay_mult) * math.sin(0.5 * math.pi * ramp)
    else:
        warm = 1.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return warm * math.exp((1 - t) * math.log(lr_init) + t * math.log(lr_final))
