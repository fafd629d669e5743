"""Control: limits and references (MTPA, field weakening), current and speed controllers,
the I-f start-up, field-oriented control and the dual three-phase current control.
Private: the public names are re-exported by `pmsmjax`."""
