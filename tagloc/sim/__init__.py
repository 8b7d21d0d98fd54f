"""The simulator: walks, floors, the camera renderer and whole sessions, and map generation."""
