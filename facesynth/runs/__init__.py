"""Training runs: the Hydra structured configs (:mod:`facesynth.runs.config`), the training
job behind ``train.py`` (:mod:`facesynth.runs.training`), the run folder's lock
(:mod:`facesynth.runs.lock`) and the Hydra callbacks (:mod:`facesynth.runs.hydra_callbacks`).
The run folder's layout and reader sit below evaluation and export, in :mod:`facesynth.rundir`."""
