"""``risp-task diagnose``: what the simulator gets wrong in measured data, the cause, and the gain.

Modules: ``run`` (the pipeline: DiagnoseConfig -> diagnose), ``fit`` (multiple shooting, Levenberg–Marquardt
with forward-mode Jacobians, noise estimation), ``candidates`` (base model and effect candidates),
``select`` (held-out BIC, noise-floor bootstrap, decision), ``residuals`` (per-channel residual analysis),
``report`` (report.md/json and plots), ``adapter`` (measured data <-> simulator states), ``synth``
(synthetic measured data with a hidden effect).  Method: docs/diagnose.md.  Nothing is imported here.
"""
