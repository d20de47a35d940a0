"""What a launch asks of a scheduler, checked before the jobs are submitted (`slurm_check`)."""
