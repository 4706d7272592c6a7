"""What a person watches (issue #34: one room): `monitor`, the model of a running rig fed with the wire's
messages (no network: tested without Zenoh); `screen`, its terminal screen; `plots`, every PNG figure
(matplotlib, imported only when a figure is drawn). The processes that show them: services/observe/."""
