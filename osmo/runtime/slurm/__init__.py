"""The Slurm runtime family: an attempt is one batch job, submitted from a login host.

- ``runtime`` — the runtime (:class:`SlurmRuntime`): launch, start, status, kill, exec,
  port-forward, clean-up of an attempt's job.
- ``commands`` — the only module that runs Slurm's commands (sbatch, squeue, scancel,
  sinfo, scontrol, srun) and parses what they print.
- ``script`` — the batch script and sbatch's options of an attempt (pure).
- ``states`` — Slurm's job states in osmo's terms: the one table.
- ``agent`` — what the job runs on its compute node (standard library only).
- ``watch`` — the local process that stands for a job on the login host (standard library
  only).
"""

from osmo.runtime.slurm.commands import JobInfo, Partition, Slurm, SlurmError
from osmo.runtime.slurm.runtime import SlurmJob, SlurmRuntime

__all__ = ["JobInfo", "Partition", "Slurm", "SlurmError", "SlurmJob",
           "SlurmRuntime"]
