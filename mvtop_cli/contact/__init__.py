"""Signed distance between object and environment, and the contact likelihood (eq. 8-9)."""
