"""What a denoiser is fitted to: the losses (`losses`), the temporal loss of sequences (`temporal`) and the
objectives that combine them per data kind (`terms`). Below the data kinds, which name their objective, and
below the trainer, which minimises it."""
