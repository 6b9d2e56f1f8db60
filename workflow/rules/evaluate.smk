# Score a phantom subject's outputs against its ground truth (phantom study only).


rule evaluate:
    input:
        unpack(evaluation_inputs),
    output:
        json="results/{subject}/evaluation.json",
        tsv="results/{subject}/evaluation.tsv",
        md=report("results/{subject}/evaluation.md", caption="../report/evaluation.rst", category="Evaluation"),
    params:
        evaluate=config["evaluate"],
        sessions=lambda wc: phantom_session_names(wc.subject),
    wildcard_constraints:
        subject=_alternatives(PHANTOM_SUBJECTS) or "(?!x)x",
    log:
        "logs/{subject}/evaluate.log",
    benchmark:
        "benchmarks/{subject}/evaluate.tsv"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../../scripts/evaluate.py"
