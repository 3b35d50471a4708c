"""Closed-loop evaluation of keyframe policies in the generation tasks."""
