"""Studies: what is compared (stimuli, comparisons), the design, state, results and exports."""
