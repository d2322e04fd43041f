"""facesynth.runtime"""
