"""Helpers shared by the cpalgo algorithms (masked rollout buffer, the PPO update, policy forward passes)."""
