"""What users run: live on the vest, replay of a recorded session, and the bundled demo."""
