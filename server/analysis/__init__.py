"""The analysis engine: the pure statistics of a study's answers (numpy/scipy, no database).

The scale of the conditions (``ranking``, ``interval_scale``), the per-condition statistics (``statistics``),
adaptive designs (``adaptive``), observer screening and its calibration to the design (``screening``,
``screening_design``), the P.910/P.913 subject model (``subject_model``), simulated observers run through the
real design code (``simulate``), and for threshold designs the psychometric function, detection per level and the
cost/quality frontier (``psychometric``, ``frontier_plot``) with planted observers through constant stimuli and
QUEST+ (``thresholds``).  It imports from ``server`` only the study definition it works on (the answer
scale ``studies.scale``, the design ``studies.design`` and the pairs it shows ``studies.assign``, the
``[screening]`` block ``studies.screening``); nothing in ``studies`` imports it.
"""
