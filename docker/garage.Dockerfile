# syntax=docker/dockerfile:1
# Garage (the S3-compatible object store of docker/compose.yaml) with a shell around it: the
# official image is the bare binary, and the nodes' entrypoint and the one-shot bucket/key service
# need sh. Same version as scripts/garage.sh installs for the tests.
ARG GARAGE_IMAGE=dxflrs/garage:v2.5.0
ARG RUNTIME_IMAGE=debian:bookworm-slim

FROM ${GARAGE_IMAGE} AS garage

FROM ${RUNTIME_IMAGE}
COPY --from=garage /garage /usr/local/bin/garage
COPY --chmod=0755 docker/garage-node.sh /usr/local/bin/garage-node
COPY --chmod=0755 docker/garage-init.sh /usr/local/bin/garage-init
# Named volumes mounted here take this ownership on first use.
RUN groupadd --system --gid 10002 garage \
 && useradd --system --uid 10002 --gid garage --no-create-home --home-dir /nonexistent \
      --shell /usr/sbin/nologin garage \
 && mkdir -p /var/lib/garage/meta /var/lib/garage/data \
 && chown -R garage:garage /var/lib/garage
USER 10002:10002
ENTRYPOINT ["/usr/local/bin/garage-node"]
