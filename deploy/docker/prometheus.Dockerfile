# Prometheus from Debian's package, for hosts that cannot pull prom/prometheus (see build-base.sh).
# Same entry point and paths as prom/prometheus, so docker-compose.yml's `command:` works with either image.
ARG BASE_IMAGE=user-base:trixie
FROM ${BASE_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends prometheus \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /prometheus && chown prometheus:prometheus /prometheus
USER prometheus
WORKDIR /prometheus
EXPOSE 9090
ENTRYPOINT ["/usr/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
