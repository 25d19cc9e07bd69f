"""Seed 002: paired coarse/fine cloth simulation, DeformTransformer detail synthesis, collision refinement."""
