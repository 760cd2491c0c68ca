"""The ENVISAT MJCF model, shipped as package data (read it with envisat_pose.geometry.model_path)."""
