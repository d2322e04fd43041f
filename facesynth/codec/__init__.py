"""facesynth.codec: geometry videos and the 16-bit PDP codec.

- :mod:`~facesynth.codec.geometry`: UV-layout rasterisation, sample-back, fill, 16-bit quantiser.
- :mod:`~facesynth.codec.sources`: ICT blendshape sequences, synthetic height fields.
- :mod:`~facesynth.codec.intra`, :mod:`~facesynth.codec.transform`, :mod:`~facesynth.codec.transform8`,
  :mod:`~facesynth.codec.entropy`, :mod:`~facesynth.codec.blocks`, :mod:`~facesynth.codec.frame`
  (decoder, serialisation), :mod:`~facesynth.codec.encoder` (RD encoder): the codec's parts.
- :mod:`~facesynth.codec.bitstream`: ``encode_video`` / ``decode_video`` and the ``.fsgv`` format.
- :mod:`~facesynth.codec.rd`: RD sweeps, BD-rate, plots; :mod:`~facesynth.codec.cli`: ``facesynth codec``.
"""
