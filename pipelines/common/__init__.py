"""What the jobs share below them: a job's defaults from a named scenario (job_defaults)."""
