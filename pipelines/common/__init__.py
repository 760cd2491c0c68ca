"""What the jobs share below them: a job's defaults from a named scenario (job_defaults) and the dataset verbs' --skip-damaged flag (dataset_inputs)."""
