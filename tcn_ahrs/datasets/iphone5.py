"""The iPhone 5 recordings of the smartphone attitude benchmark (Michel et al., PerCom 2017) in the
generic format (``../shared/datasets/phones/iphone5``; conversion and caveats in its README): read by the
generic loader, named as the device (``data=iphone5``, conf/data/iphone5.yaml: the split by user)."""
from .generic import device_loader, list_recordings

__all__ = ["list_recordings", "load_recording"]
load_recording = device_loader("iphone5")
