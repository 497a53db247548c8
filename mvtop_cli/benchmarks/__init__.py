"""Measurements of mvtop on this machine, apart from the estimator (nothing in ``estimator``,
``filter`` or ``pipelines`` imports this package): ``accuracy`` (simulated grasps, every
method), ``long_log`` (memory and time on a long log), ``render_speed`` (the batched
renderer), ``masking_speed`` (the masking backends per frame) and ``baselines`` (CHSEL)."""
