"""facesynth.model"""
