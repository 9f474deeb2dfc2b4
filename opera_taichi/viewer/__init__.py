"""See a run in 3-D in a browser: live (`run --view`), as a replay (`run --replay`, then `view RUN_DIR`), as one
self-contained HTML file (`view RUN_DIR --html F`) or as a video (`view RUN_DIR --mp4 F`).

Modules: frames (what is shown, as data), colors (particle colours and colour bar), replay (the replay file: record
and read; numpy only), view (the viser scene and panel), live (the live observer and its controller), playback (the
replay server and the HTML export), video (the MP4). viser is an optional extra: `pip install -e '.[viewer]'`.
"""
