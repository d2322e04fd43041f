"""facesynth.eri"""
