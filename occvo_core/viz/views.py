"""Several views as one (a rerun viewer, an MCAP file, a Foxglove server, a ROS 2 bag side by side): each call goes
to every view that has that method."""

from __future__ import annotations


class Views:
    def __init__(self, views: list):
        self.views = list(views)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)

        def call(*args, **kwargs) -> None:
            for view in self.views:
                method = getattr(view, name, None)
                if method is not None:
                    method(*args, **kwargs)

        return call
