"""Tests for the agents package."""
