"""Training runs: the Hydra structured configs (:mod:`facesynth.runs.config`), the run
directory (:mod:`facesynth.runs.rundir`: layout, data, training landmarks, summaries), the
training job behind ``train.py`` (:mod:`facesynth.runs.training`), the run folder's lock
(:mod:`facesynth.runs.lock`) and the Hydra callbacks (:mod:`facesynth.runs.hydra_callbacks`)."""
