"""The view graph as the averaging sees it: its component, its checks, and the evidence behind each camera."""
