"""recorder: MCAP recording of Zenoh keys (requirement LOG-1; MCAP, where the source had rosbag2).

One channel per key, our msgpack payloads byte for byte with the schema name/version and a JSON
Schema in the schema record; presets, zstd chunks flushed at least every second (a kill -9 loses
at most that), splits at max_bag_size. It must never slow the stack: a bounded buffer drops
(and counts) what the disk cannot take, and a disk error stops only the recording.
"""
