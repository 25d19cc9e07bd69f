"""Seed 000: multiscale deformation components with stacked attention-based autoencoders."""
