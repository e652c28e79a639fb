"""Tests of the camera and recording sources (services/detector/cameras)."""
