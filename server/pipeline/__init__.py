"""From motion files and study files to a study's videos: the stimulus pipeline (:mod:`.stimuli`), the kinds of
job that run it (:mod:`.jobs`) and the build of a study's uploads (:mod:`.assets`)."""
