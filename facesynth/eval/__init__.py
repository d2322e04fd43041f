"""facesynth.eval"""
