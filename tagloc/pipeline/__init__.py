"""The localiser (one frame through the stages and the tracker), the session loop, live and replay."""
