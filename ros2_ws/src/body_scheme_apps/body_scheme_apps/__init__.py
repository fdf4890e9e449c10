"""Applications of the body scheme suite, apart from the libraries: experiments, demos, benchmarks, replay reports and
recording (docs/architecture.md)."""
