"""Prediction models: the RHONN (paper eq. 5-8, 17) and the physics baselines (bicycle, 7-DoF, MF
tyres).
"""
