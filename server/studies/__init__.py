"""Studies: the study definition: what is compared (stimuli, comparisons), the design, the answer scale, state,
and the statistics as pure functions (the results and exports, which read the votes, are :mod:`server.research`)."""
