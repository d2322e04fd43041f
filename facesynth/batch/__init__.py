"""Many subjects at once: ``facesynth batch`` turns a folder of videos into trained,
evaluated and exported avatars, one folder per subject, plus a summary table and plot.

* :mod:`~facesynth.batch.discover` finds the videos and names the subjects;
* :mod:`~facesynth.batch.state` decides, from each stage's outputs, whether a stage is
  complete and valid (what makes a re-run resumable);
* :mod:`~facesynth.batch.job` runs one subject: ingest -> train + evaluate -> export;
* :mod:`~facesynth.batch.executor` runs the jobs as Ray tasks (local runtime or a
  cluster), or one after another when Ray is not installed;
* :mod:`~facesynth.batch.summary` writes ``summary.csv``, ``summary.md`` and the plot;
* :mod:`~facesynth.batch.cli` is ``facesynth batch``.
"""
