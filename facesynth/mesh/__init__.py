"""facesynth.mesh"""
