"""facesynth.codec"""
