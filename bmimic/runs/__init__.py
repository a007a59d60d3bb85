"""The run folder and its record: file names and paths (folder), what the files hold (schema), the
training's writer of its tables (record), a launch's claim on its folder (claim), a race's record
(race_record) and the project's one atomic writer (atomic_io). Torch-free: the analysis reads runs
through these modules alone."""
