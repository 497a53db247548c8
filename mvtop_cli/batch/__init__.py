"""Many logs, one command: the batch engine behind ``mvtop estimate`` over several logs and
``mvtop benchmark accuracy``.

- ``jobs``: the job list (LOG arguments, folders, glob patterns, a CSV or YAML manifest), one
  job per log with its config and options and its own output folder.
- ``engine``: where jobs run: in this process, a pool of local worker processes, or Ray tasks
  on a local Ray instance or a cluster (``ray`` is the optional extra ``mvtop[ray]``).
- ``run``: the estimate job as it runs on a worker (its outputs, a record of the run), the
  driver (resume, retries, progress) and the results table ``runs.csv``.
"""
