"""facesynth.sadm"""
