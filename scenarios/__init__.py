"""The named scenarios as TOML package data (`envisat_pose.scenarios`); read by envisat_pose.named_scenarios."""
