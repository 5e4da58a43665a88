"""The high-gain design K(ε) in the special coordinate basis (Sec. III-A.2, III-B.2, corrigendum).

:mod:`.gains` designs K(ε) for observer (3) (SISO and MIMO chains), :mod:`.design_system`
designs on a simplified system and checks the gains on the true one (Secs. VII–VIII).

What it may import: :mod:`thetahat.structure`, :mod:`thetahat.model` and the package's
helpers. Never the estimators: an observer reads any object with ``K_x`` and ``K_phi``.
"""
