"""Authenticated, authorised Zenoh for a team: a private CA, certificates and role configs.

:func:`~.certificates.write_secure_dir` (``relloc secure init``) writes, for one team config:

* ``ca.pem`` and ``ca.key``: a private certificate authority (EC P-256, self-signed);
* per role a certificate ``<role>.pem`` signed by it (common name = the role) and a Zenoh
  JSON5 config ``<role>.json5``: mutual TLS on ``tls/`` endpoints only (the CA, the role's
  certificate and its private key embedded in base64, so that the file alone is what a
  machine needs) and the team's access control. The roles are ``serve``, ``navigate``,
  ``team`` (``sim-robots`` and ``replay``, which speak for the whole team) and
  ``robot-<name>`` per robot.

Private keys (``ca.key`` and every ``.json5``) are written readable by the owner only. Every
certificate names ``localhost``, ``127.0.0.1`` and the given hosts (any role may listen in
peer mode).

The access control is the same in every file, because each Zenoh node judges what reaches it
by the common name of the certificate on the link it came from (``ingress``): by default
nothing may be published (``put``/``delete``); a robot may publish its own topics (its
odometry, the ranges its UWB node measures, its detections and sightings), ``team`` every
robot topic and the motion capture, ``serve`` the estimates (``relloc/**``), ``navigate`` the
commanded robots' ``cmd_vel``. Declarations (subscribers, liveliness tokens, queries) are
allowed between team members: they let a member receive, never speak. A node forwarding for
others is judged as itself, so the members must link directly (a full mesh of endpoints).

Zenoh reports a refusal only in its trace log (``zenoh::net::routing::interceptor::
access_control``, on stdout: ``... CertCommonName(r1) ... is unauthorized to Put (ingress) on
r2/odom``); :class:`~.refusals.AccessRefusals` captures that stream and counts them.

=====================  ====================================================================
:mod:`.access`         the roles, who may publish what, the ACL and a role's Zenoh config
:mod:`.certificates`   the CA, the certificates and :func:`~.certificates.write_secure_dir`
:mod:`.identity`       :func:`~.identity.security_of`: a session's :class:`~.identity.Security`
:mod:`.refusals`       :class:`~.refusals.AccessRefusals`: what the access control refused
=====================  ====================================================================
"""
