"""nrbench's SLURM launcher for Hydra: submitit's, telling a job when it is requeued (slurm_launcher.py)."""
