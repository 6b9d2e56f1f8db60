# Study report: one self-contained HTML page per subject (atlases, quality, 3-D views, changes).


rule report:
    input:
        unpack(report_inputs),
    output:
        html=report(
            "results/{subject}/report.html",
            caption="../report/study_report.rst",
            category="Study report",
            labels={"subject": "{subject}"},
        ),
    params:
        report=config["report"],
        sessions=lambda wc: report_sessions(wc.subject),
        pairs=lambda wc: [list(p) for p in comparison_pairs(wc.subject)],
    log:
        "logs/{subject}/report.log",
    benchmark:
        "benchmarks/{subject}/report.tsv"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../../scripts/report.py"
