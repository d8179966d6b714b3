"""The clip set on disk: the clip-set file (:mod:`.config`), reading its sources from the data directory and
building it (:mod:`.build`), and the clip manifest with one ``.npz`` per clip (:mod:`.manifest`)."""
