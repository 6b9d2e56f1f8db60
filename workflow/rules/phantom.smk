# Built-in phantom: render one session's video and ground truth (default study).


rule phantom_session:
    output:
        video="results/{subject}/phantom/{session}/video.mp4",
        truth=directory("results/{subject}/phantom/{session}/truth"),
    params:
        phantom=config["phantom"],
        camera=phantom_camera(),
    wildcard_constraints:
        subject=_alternatives(PHANTOM_SUBJECTS) or "(?!x)x",
    log:
        "logs/{subject}/phantom/{session}.log",
    benchmark:
        "benchmarks/{subject}/phantom/{session}.tsv"
    threads: config["phantom"]["threads"] or 2  # 0 = the machine's cores, at most 2
    resources:
        mem_mb=4000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../../scripts/phantom_session.py"
