"""The torch-free runtime: run exported synthesis models with ONNX Runtime.

Imports only numpy, onnxruntime and OpenCV (a test checks that torch stays unimported)::

    from facesynth.runtime import Renderer
    r = Renderer("model.onnx", threads=1)
    crops, masks, placements = r.render(landmarks)      # (B, 68, 2) frame pixels
    frame = r.render_frame(landmarks[0], background)     # uint8 (H, W, 3)

    re = Reenactor("avatar.onnx")                        # another face drives the avatar
    frame, avatar_lm = re.step(driver_lm)                # (68, 2) -> uint8 frame in the avatar's own frame

    th = TalkingHead("head.onnx", driver_neutral=lm0)   # the whole talking head in one graph
    frame, avatar_lm = th.step(driver_lm)

    p = AvatarPipeline("avatar.onnx")                    # facesynth app's per-frame work, either file
    p.start(driver_neutral, background=p.avatar.background)
    frames = p.frames(driver_landmarks)                  # (T, P, 2) -> uint8 (H, W, 3) each

    e = EriRenderer("eri.onnx")                          # an ERI model (one target face)
    frames = e.render_frames(faps, target_image)         # (B, 36) MPEG-4 FAPs -> uint8 (B, H, W, 3)
"""

from facesynth.compositing import composite
from facesynth.runtime.eri import EriRenderer
from facesynth.runtime.filters import OneEuroFilter, smooth_landmarks
from facesynth.runtime.pipeline import AvatarPipeline
from facesynth.runtime.reenact import Reenactor
from facesynth.runtime.renderer import Renderer, read_metadata
from facesynth.runtime.talking_head import TalkingHead

__all__ = ["AvatarPipeline", "EriRenderer", "OneEuroFilter", "Reenactor", "Renderer", "TalkingHead", "composite", "read_metadata",
           "smooth_landmarks"]
