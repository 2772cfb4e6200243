"""/diagnostics says which query budget the outputs ran: the last output's budget and the
mean share of the queries refined over the window (online/diagnostics.py)."""
from odg_ros.online import diagnostics


def test_the_budget_of_the_outputs_is_reported():
    clock = [0.0]
    stats = diagnostics.PipelineStats(clock=lambda: clock[0])
    values = dict(stats.status({})["values"])
    assert values["query_budget (last output)"] == "n/a"
    assert values["queries_refined_percent (mean)"] == "n/a"
    for k, (budget, fraction) in enumerate([("full", 1.0), ("s120-d52", 0.5733),
                                            ("s72-d28", 0.3333)]):
        clock[0] = 0.1 * k
        stats.record_output(image_stamp=clock[0], now=clock[0], timings={},
                            query_budget=budget, refined_fraction=fraction)
    values = dict(stats.status({})["values"])
    assert values["query_budget (last output)"] == "s72-d28"
    assert values["queries_refined_percent (mean)"] == "63.6"
