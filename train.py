"""Train and evaluate a per-subject facesynth model (Hydra): the same app as ``facesynth train``.

    python train.py                                   # synthetic subject, krr SADM (the default regressor)
    python train.py data=video data.path=DIR regressor=svr
    python train.py experiment=rigid_features data=video data.path=DIR   # a named study
    python train.py -m regressor=krr,linear,poly2,mlp,svr data=video data.path=DIR   # sweep + table
    python train.py model=eri data=video data.path=DIR                          # an ERI model instead

The configs live in the package (``facesynth/conf``). Ctrl-C prints "interrupted" and exits
130 (SIGTERM: "terminated", 143); bad input is one line ``error: ...`` and exit 2, a run
folder in use by another train.py too.
"""

import sys

from facesynth.runs.train_cli import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], prog="train.py"))
