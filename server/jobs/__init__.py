"""The job system: one job table (:mod:`.models`), one runner (:mod:`.runner`), one claim/resume rule and the
control of job processes (:mod:`.control`), progress and outcome (:mod:`.progress`).  It knows no kind of job:
the kinds are registered once, in :data:`server.pipeline.jobs.KINDS`."""
