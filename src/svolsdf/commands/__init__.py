"""svolsdf.commands: what the commands over runs do, above the pipeline and the components.

`render` (novel views of a finished run), `benchmark` (scenes x modes into one table) and its
`executors` (in this process, or Ray tasks), and `mvs` (the MVS cascade alone on a scene, then
fusion: ``svolsdf mvs``). They open runs through `svolsdf.pipeline.Run` or run
`svolsdf.pipeline.Pipeline`; no component package imports them or the pipeline.
"""
