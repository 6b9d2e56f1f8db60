# Stage 1: decode the video and keep sharp, well-exposed, non-redundant frames.


rule frames:
    input:
        video=session_video,
    output:
        frames=directory("results/{subject}/{session}/frames"),
    params:
        frames=config["frames"],
        camera=session_camera,
    log:
        "logs/{subject}/{session}/frames.log",
    benchmark:
        "benchmarks/{subject}/{session}/frames.tsv"
    threads: session_threads(config["frames"]["threads"])
    resources:
        mem_mb=2000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../../scripts/frames.py"
