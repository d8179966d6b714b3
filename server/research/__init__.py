"""Research: a study together with its participants, as its researcher sees it: summaries, results, exports,
and the researcher's API over studies."""
