"""Training: the trainer, what it reads from a recording (plain arrays), density control, losses and
schedules."""
