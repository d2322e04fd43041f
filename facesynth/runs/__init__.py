"""Training runs: the Hydra structured configs (:mod:`facesynth.runs.config`), the run
directory (:mod:`facesynth.runs.rundir`: layout, data, training landmarks, summaries), the
training job behind ``train.py`` (:mod:`facesynth.runs.training`) and the sweep callback
(:mod:`facesynth.runs.hydra_callbacks`)."""
