"""The Zenoh wire protocol between processes: key expressions (`keys`), the frame format with its zero-copy
encode/decode and validation (`codec`, `schema`), one module per message family (`trajectories`, `weights`,
`credits`, `levels`, `status`, `control`) with the `Stamp` every frame carries, session configuration and
liveliness (`session`, `inbox`), the roles and what each may ask and hear (`roles`), and routers (`router`). It
depends only on numpy and zenoh, so both ends of every message agree on one definition and it can be tested
without a model or an engine."""
