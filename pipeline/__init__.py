"""The calibration method (paper Sec. III) and the scenario simulator: pure functions over arrays and schemas.

Never imports zenoh or mcap, never touches the network; file reading lives in `pipeline.loaders` only.
"""
