"""Pipelines that wire io to the core: estimate, evaluate, render-masks, simulate."""
