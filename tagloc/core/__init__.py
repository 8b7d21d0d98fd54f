"""The bottom layer: shared types (frames, detections, fixes, tracker output), the sticker, map, camera and rig, geometry and errors."""
