"""Benchmarks (``make bench``): speed and accuracy at full size, tables under results/bench/.

Times are medians over repeats, measured in one run so that the machine's load is shared
alike; each table also records the machine (cores, load) it was measured on.
"""
