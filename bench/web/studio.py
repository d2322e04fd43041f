"""The studio's time from pressing Record to the first live frame of the new avatar.

Serves ``facesynth studio`` on 127.0.0.1 with a fresh library, opens it in headless system
Chromium with ``--video`` (its first ``--frames`` frames, looped) as the fake camera, presses
Record and follows every prompt (``--seconds`` times each prompt's duration: 1 is the page's
script, about 40 s), names the avatar, presses Train and waits for the first frame the new avatar
renders live. The training is the studio's default configuration unless ``--small`` (the
flow test's). Prints ONE JSON line:

* ``record_s``: Record pressed -> the last prompt recorded; ``upload_to_live_s``: Train
  pressed -> the first live frame (upload, training job, loading the avatar, the neutral capture);
  ``total_s``: Record pressed -> the first live frame; ``report_after_live_s``: the first live
  frame -> the run's report written (the evaluation and report, made while the avatar drives);
* ``job_s``, ``job_cpu_s``: the training job's stages as it measured them, wall-clock and CPU
  seconds (every thread of the job's process); ``frames``: the recording's frames;
  ``coverage``: the prompt bars' mean; ``self_reach``: the page's headline (held-out reach);
* ``load``: the host's 1-minute load average at the start and the end (the machine is shared).

    python -m bench.web.studio --video CLIP.mp4 [--seconds 1] [--small]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from bench.harness import load_average


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--video", required=True)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--seconds", type=float, default=1.0, help="each prompt's duration times this")
    p.add_argument("--small", action="store_true", help="the flow test's small training configuration")
    p.add_argument("--shots", default=None, help="folder for the screenshots of each step")
    a = p.parse_args()

    from bench import browser

    load0 = load_average()
    with tempfile.TemporaryDirectory() as tmp:
        cam = Path(tmp) / "cam.y4m"
        browser.write_y4m(a.video, cam, a.frames, (640, 480))
        with browser.studio_served(Path(tmp) / "lib", overrides=browser.STUDIO_SMALL if a.small else (), min_frames=10) as (url, _), \
                browser.browser_page(cam) as (page, blocked):
            t = browser.run_studio_flow(page, url, "bench", a.seconds, Path(a.shots) if a.shots else None, timeout_s=1800)
    summary = t["job"].get("summary", {})
    print(json.dumps({
        "record_s": round((t["recorded"] - t["record"]) / 1000, 1),
        "upload_to_live_s": round((t["first_frame"] - t["train_pressed"]) / 1000, 1),
        "total_s": round((t["first_frame"] - t["record"]) / 1000, 1),
        "report_after_live_s": round((t["report_written"] - t["first_frame"]) / 1000, 1),
        "job_s": summary.get("seconds"), "job_cpu_s": summary.get("cpu_seconds"), "frames": summary.get("frames"),
        "coverage": round(t["coverage"]["overall"], 3), "self_reach": round(t["coverage"]["self_reach"], 3),
        "small": a.small, "prompt_scale": a.seconds,
        "offline": not blocked, "load": [round(load0, 1), round(load_average(), 1)],
    }))


if __name__ == "__main__":
    main()
