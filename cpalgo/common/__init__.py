"""Helpers shared by the cpalgo algorithms (masked rollout buffer, policy forward passes)."""
